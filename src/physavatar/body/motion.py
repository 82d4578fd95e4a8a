"""Motions: per-frame bone rotations + root translation at an fps, and the built-in ones.

A motion's rotations are axis-angle vectors in world-aligned axes, one per Anny bone (see
``body/model.py``); bones a motion does not move stay at zero. Built-in motions are smooth
functions of time that start at the rest pose and ease in over the first half second, so a
cloth simulation can start at rest (paper Sec. 3.2, "Animation").

Axes of the body (Anny): z up, the body faces -y, its left is +x. So, for a bone hanging down,
a rotation about +x by a negative angle swings it forward (towards -y).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import PhysavatarError
from ..files import load_npz, save_npz_atomic
from .model import BodyModel, axis_angle_to_matrix, bone_vertex_mask, matrix_to_axis_angle


@dataclass
class Motion:
    """A motion of the Anny skeleton.

    Attributes:
        name: a label.
        fps: frames per second.
        bone_names: [B] Anny bone labels, in the order of ``rotations``' second axis.
        rotations: [T, B, 3] axis-angle per bone (world-aligned axes), radians.
        root_translation: [T, 3] metres.
    """

    name: str
    fps: float
    bone_names: list[str]
    rotations: np.ndarray
    root_translation: np.ndarray
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.rotations = np.asarray(self.rotations, dtype=np.float64)
        self.root_translation = np.asarray(self.root_translation, dtype=np.float64)
        self.bone_names = [str(b) for b in self.bone_names]
        B = len(self.bone_names)
        if self.rotations.ndim != 3 or self.rotations.shape[1:] != (B, 3):
            raise ValueError(f"motion rotations must have shape [T, {B}, 3], got {self.rotations.shape}")
        if self.root_translation.shape != (self.rotations.shape[0], 3):
            raise ValueError(
                f"motion root_translation must have shape [{self.rotations.shape[0]}, 3], "
                f"got {self.root_translation.shape}")
        if not (np.isfinite(self.rotations).all() and np.isfinite(self.root_translation).all()):
            raise ValueError("motion contains NaN or infinite values")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"motion fps must be positive, got {self.fps}")

    @property
    def frames(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def duration(self) -> float:
        return (self.frames - 1) / self.fps

    # -- io -----------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        save_npz_atomic(path, name=np.array(self.name), fps=np.array(self.fps, dtype=np.float64),
                        bone_names=np.array(self.bone_names), rotations=self.rotations,
                        root_translation=self.root_translation)

    @staticmethod
    def load(path: str | Path) -> "Motion":
        path = Path(path)
        z = load_npz(path)
        missing = [k for k in ("fps", "bone_names", "rotations", "root_translation") if k not in z]
        if missing:
            raise PhysavatarError(path, f"motion file lacks arrays {missing}")
        try:
            return Motion(str(z.get("name", path.stem)), float(z["fps"]), list(z["bone_names"]),
                          z["rotations"], z["root_translation"])
        except ValueError as e:
            raise PhysavatarError(path, str(e)) from None

    # -- operations ---------------------------------------------------------------------------
    def for_bones(self, bone_names: list[str]) -> "Motion":
        """The same motion over another bone list (missing bones stay at rest)."""
        idx = {b: i for i, b in enumerate(self.bone_names)}
        R = np.zeros((self.frames, len(bone_names), 3))
        for j, b in enumerate(bone_names):
            if b in idx:
                R[:, j] = self.rotations[:, idx[b]]
        return Motion(self.name, self.fps, bone_names, R, self.root_translation, dict(self.meta))

    def resample(self, fps: float) -> "Motion":
        """Resample to ``fps``: spherical interpolation of rotations, linear of translations."""
        if abs(fps - self.fps) < 1e-9:
            return self
        n = int(np.floor(self.duration * fps + 1e-9)) + 1
        t = np.arange(n) / fps * self.fps  # fractional source frame
        i0 = np.clip(np.floor(t).astype(int), 0, self.frames - 1)
        i1 = np.clip(i0 + 1, 0, self.frames - 1)
        a = (t - i0)[:, None]
        rot = slerp_rotations(self.rotations[i0], self.rotations[i1], a)
        tr = (1 - a) * self.root_translation[i0] + a * self.root_translation[i1]
        return Motion(self.name, fps, self.bone_names, rot, tr, dict(self.meta))

    def slice(self, start: int, stop: int) -> "Motion":
        return Motion(self.name, self.fps, self.bone_names, self.rotations[start:stop],
                      self.root_translation[start:stop], dict(self.meta))

    def pose(self, body: BodyModel):
        """Pose ``body`` with this motion -> PosedBody."""
        m = self.for_bones(body.bone_names) if self.bone_names != body.bone_names else self
        return body.pose(m.rotations, m.root_translation)


def slerp_rotations(r0: np.ndarray, r1: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Axis-angle rotations [..., B, 3] a fraction ``a`` [..., 1] of the way from ``r0`` to ``r1``
    along the shortest arc of each bone's rotation (R0 exp(a log(R0ᵀ R1))): how a motion is
    resampled (:meth:`Motion.resample`) and how sim sub-steps pose the body in between frames
    (body.between)."""
    R0 = axis_angle_to_matrix(r0)
    R1 = axis_angle_to_matrix(r1)
    rel = matrix_to_axis_angle(np.swapaxes(R0, -1, -2) @ R1)
    return matrix_to_axis_angle(R0 @ axis_angle_to_matrix(rel * np.asarray(a)[..., None]))


# -- built-in motions ----------------------------------------------------------------------------

def _ease(t: np.ndarray, ramp: float = 0.5) -> np.ndarray:
    """0 at t=0 rising smoothly (C1) to 1 at t=ramp: motions start at rest."""
    s = np.clip(t / ramp, 0.0, 1.0)
    return s * s * (3 - 2 * s)


def world_rotations(r: np.ndarray, parents) -> np.ndarray:
    """[T, B, 3, 3] each bone's world rotation relative to rest from the per-bone axis-angle
    rotations ``r`` [T, B, 3] (world-aligned local rotations: X_b = X_parent R_b)."""
    R = axis_angle_to_matrix(r)
    X = np.empty_like(R)
    for b in range(r.shape[1]):
        X[:, b] = R[:, b] if parents[b] < 0 else X[:, parents[b]] @ R[:, b]
    return X


def turn_bone(r: np.ndarray, b: int, Xp: np.ndarray, vec: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """``r`` [T, B, 3] with bone ``b`` turned about its joint by the world rotation vectors ``vec``
    [len(frames), 3] in ``frames`` (``Xp``: the parent's world rotations there, which this leaves
    unchanged)."""
    out = r.copy()
    Q = axis_angle_to_matrix(vec)
    out[frames, b] = matrix_to_axis_angle(np.swapaxes(Xp, 1, 2) @ Q @ Xp @ axis_angle_to_matrix(r[frames, b]))
    return out


def _x(a):  # axis-angle about world x
    return np.stack([a, np.zeros_like(a), np.zeros_like(a)], -1)


def _y(a):
    return np.stack([np.zeros_like(a), a, np.zeros_like(a)], -1)


def _z(a):
    return np.stack([np.zeros_like(a), np.zeros_like(a), a], -1)


def _idle(t, e):
    w = 2 * np.pi * 0.25
    return {
        "spine03": _x(0.03 * np.sin(w * t) * e),
        "spine01": _y(0.03 * np.sin(0.5 * w * t) * e),
        "upperarm01.L": _y(-0.05 * (1 - np.cos(w * t)) * e),
        "upperarm01.R": _y(0.05 * (1 - np.cos(w * t)) * e),
        "neck01": _z(0.1 * np.sin(0.3 * w * t) * e),
    }, np.zeros((len(t), 3))


def _walk(t, e):
    w = 2 * np.pi * 0.9  # one stride cycle per ~1.1 s
    s = np.sin(w * t)
    knee_l = 0.55 * np.clip(np.sin(w * t + 1.2), 0, None) ** 1.5
    knee_r = 0.55 * np.clip(np.sin(w * t + 1.2 + np.pi), 0, None) ** 1.5
    rot = {
        "upperleg01.L": _x(-0.45 * s * e),
        "upperleg01.R": _x(0.45 * s * e),
        "lowerleg01.L": _x(knee_l * e),
        "lowerleg01.R": _x(knee_r * e),
        "upperarm01.L": _x(0.4 * s * e),
        "upperarm01.R": _x(-0.4 * s * e),
        "lowerarm01.L": _x(-(0.25 + 0.15 * s) * e),
        "lowerarm01.R": _x(-(0.25 - 0.15 * s) * e),
        "spine03": _z(0.08 * s * e),
        "root": _z(-0.05 * s * e),
    }
    tr = np.zeros((len(t), 3))
    # The pelvis drops by the height a straight leg loses at the stride angle, so the stance
    # foot stays on the floor (0.8 m: hip-to-sole length of the default body).
    tr[:, 2] = -0.6 * (1 - np.cos(0.45 * s * e))
    return rot, tr


def _turn(t, e):
    # A full turn about the vertical at constant speed after the ease-in, with a slight step.
    ang = 2 * np.pi * 0.25 * np.cumsum(e) * (t[1] - t[0] if len(t) > 1 else 0.0)
    s = np.sin(2 * np.pi * 1.0 * t)
    return {
        "root": _z(ang),
        "upperleg01.L": _x(-0.2 * np.clip(s, 0, None) * e),
        "upperleg01.R": _x(-0.2 * np.clip(-s, 0, None) * e),
        "lowerleg01.L": _x(0.35 * np.clip(s, 0, None) * e),
        "lowerleg01.R": _x(0.35 * np.clip(-s, 0, None) * e),
    }, np.zeros((len(t), 3))


def _arm_swing(t, e):
    w = 2 * np.pi * 0.6
    s = np.sin(w * t)
    lift = 0.5 * (1 - np.cos(w * t))
    return {
        "upperarm01.L": _y(-0.9 * lift * e) + _x(0.3 * s * e),
        "upperarm01.R": _y(0.9 * lift * e) + _x(-0.3 * s * e),
        "lowerarm01.L": _x(-0.3 * lift * e),
        "lowerarm01.R": _x(-0.3 * lift * e),
    }, np.zeros((len(t), 3))


def _twist(t, e):
    w = 2 * np.pi * 0.5
    s = np.sin(w * t)
    return {
        "spine05": _z(0.25 * s * e),
        "spine03": _z(0.25 * s * e),
        "spine01": _z(0.2 * s * e),
        "root": _z(0.15 * s * e),
        "upperarm01.L": _y(-0.3 * e),
        "upperarm01.R": _y(0.3 * e),
    }, np.zeros((len(t), 3))


def _jump(t, e):
    # Periodic jump: crouch (0..0.35 of a cycle), flight (a ballistic arc), landing.
    period = 1.5
    ph = (t % period) / period
    crouch = np.where(ph < 0.35, np.sin(np.pi * ph / 0.35), 0.0)
    fly = np.where((ph >= 0.35) & (ph < 0.75), np.sin(np.pi * (ph - 0.35) / 0.4), 0.0)
    land = np.where(ph >= 0.75, np.sin(np.pi * (ph - 0.75) / 0.25), 0.0)
    bend = (crouch + 0.6 * land) * e
    tr = np.zeros((len(t), 3))
    tr[:, 2] = (0.18 * fly - 0.12 * bend) * e
    return {
        "upperleg01.L": _x(-0.7 * bend),
        "upperleg01.R": _x(-0.7 * bend),
        "lowerleg01.L": _x(1.3 * bend),
        "lowerleg01.R": _x(1.3 * bend),
        "foot.L": _x(-0.6 * bend),
        "foot.R": _x(-0.6 * bend),
        "spine05": _x(-0.25 * bend),
        "upperarm01.L": _x(0.5 * bend - 0.9 * fly * e) + _y(-0.3 * fly * e),
        "upperarm01.R": _x(0.5 * bend - 0.9 * fly * e) + _y(0.3 * fly * e),
    }, tr


def _dance(t, e):
    w = 2 * np.pi * 1.0
    s, c = np.sin(w * t), np.cos(w * t)
    s2 = np.sin(0.5 * w * t)
    tr = np.zeros((len(t), 3))
    tr[:, 0] = 0.08 * s2 * e
    tr[:, 2] = -0.03 * (1 - np.cos(2 * w * t)) * 0.5 * e
    return {
        "root": _z(0.35 * s2 * e) + _y(0.08 * s * e),
        "spine03": _y(-0.12 * s * e),
        "spine01": _z(0.2 * c * e),
        "upperarm01.L": _y(-(0.6 + 0.5 * s) * e) + _x(-0.3 * c * e),
        "upperarm01.R": _y((0.6 - 0.5 * s) * e) + _x(0.3 * c * e),
        "lowerarm01.L": _x(-(0.6 + 0.4 * c) * e),
        "lowerarm01.R": _x(-(0.6 - 0.4 * c) * e),
        "upperleg01.L": _x(-0.25 * np.clip(s, 0, None) * e) + _y(-0.1 * e),
        "upperleg01.R": _x(-0.25 * np.clip(-s, 0, None) * e) + _y(0.1 * e),
        "lowerleg01.L": _x(0.5 * np.clip(s, 0, None) * e),
        "lowerleg01.R": _x(0.5 * np.clip(-s, 0, None) * e),
        "neck01": _z(0.2 * s2 * e),
    }, tr


BUILTIN: dict[str, tuple[Callable, str]] = {
    "idle": (_idle, "standing, breathing sway and a slow head turn"),
    "walk": (_walk, "walking in place: legs, knees, counter-swinging arms, pelvis bob"),
    "turn": (_turn, "a full turn about the vertical axis while stepping"),
    "arm-swing": (_arm_swing, "both arms raised sideways and swung"),
    "twist": (_twist, "torso twisting left and right with the arms out"),
    "jump": (_jump, "repeated jumps: crouch, flight, landing"),
    "dance": (_dance, "a side-to-side dance with arm and hip movement"),
}


def builtin_motion(name: str, bone_names: list[str], fps: float = 25.0, duration: float = 4.0) -> Motion:
    """A built-in motion sampled at ``fps`` for ``duration`` seconds (``list(BUILTIN)``)."""
    if name not in BUILTIN:
        raise ValueError(f"unknown motion {name!r}; built-in motions: {', '.join(BUILTIN)}")
    n = int(round(duration * fps)) + 1
    t = np.arange(n) / fps
    e = _ease(t)
    rot_by_bone, tr = BUILTIN[name][0](t, e)
    idx = {b: i for i, b in enumerate(bone_names)}
    R = np.zeros((n, len(bone_names), 3))
    for b, r in rot_by_bone.items():
        if b not in idx:
            raise KeyError(f"built-in motion {name!r} moves bone {b!r}, which the skeleton lacks")
        R[:, idx[b]] = r
    return Motion(name, fps, bone_names, R, tr, {"source": "builtin", "duration": duration})


_ARM_PARTS = ("lowerarm", "wrist", "hand", "finger", "thumb", "metacarpal")
_TRUNK_PARTS = ("root", "pelvis", "spine", "upperleg")


def arm_clearance(motion: Motion, body: BodyModel, clearance: float = 0.03, samples_per_face: int = 10,
                  max_angle: float = np.radians(40.0)):
    """Raise the arms sideways (about the torso's forward axis, at the shoulder joint) in the
    frames where a hand or forearm comes closer than ``clearance`` [m] to the trunk (hips,
    thighs, spine), just enough to clear it, smoothed over time.

    Motion capture retargeted onto another body often rests the hands on (or in) the hips: a
    garment there is pinched with no room left, which a contact-exact simulator cannot resolve
    (docs/simulation.md, "Moving collider"). Returns (motion, info): ``info`` has the per-frame
    distance before and after [T] and the angle added per side [T] (radians).
    """
    from scipy.ndimage import gaussian_filter1d, maximum_filter1d
    from scipy.spatial import cKDTree

    m = motion.for_bones(body.bone_names)
    rots, trs = m.rotations.copy(), m.root_translation
    names = body.bone_names
    idx = {n: i for i, n in enumerate(names)}
    F = np.asarray(body.faces)
    trunk = bone_vertex_mask(body, _TRUNK_PARTS)
    trunk_faces = F[np.all(trunk[F], axis=1)]
    bary = np.random.default_rng(0).dirichlet([1.0, 1.0, 1.0], size=(len(trunk_faces), samples_per_face))
    parents = body.parents

    def distances(r, arm):
        V = body.pose(r, trs).vertices
        out = np.empty(len(V))
        for t in range(len(V)):
            P = np.einsum("fsk,fkd->fsd", bary, V[t][trunk_faces]).reshape(-1, 3)
            out[t] = cKDTree(P).query(V[t][arm])[0].min()
        return out

    def rotated(r, b, Xp, axis, theta):  # Xp: the parent's world rotations (unchanged by this)
        return turn_bone(r, b, Xp, axis * theta[:, None], np.arange(len(r)))

    info = {}
    for side in ("L", "R"):
        b = idx.get(f"upperarm01.{side}")
        arm = bone_vertex_mask(body, [n for n in names if n.startswith(_ARM_PARTS) and n.endswith(f".{side}")])
        if b is None or not arm.any() or not len(trunk_faces):
            continue
        # the torso's forward axis (the body faces -y at rest) and the shoulder's rotation, per frame
        X = world_rotations(rots, parents)
        axis = X[:, idx.get("spine01", 0)] @ np.array([0.0, -1.0, 0.0])
        Xp = X[:, parents[b]]
        d0 = distances(rots, arm)
        need = d0 < clearance
        theta = np.zeros(len(rots))
        if need.any():
            probe = np.full(len(rots), 0.2)
            sign = 1.0 if distances(rotated(rots, b, Xp, axis, probe), arm)[need].mean() >= \
                distances(rotated(rots, b, Xp, axis, -probe), arm)[need].mean() else -1.0
            lo, hi = np.zeros(len(rots)), np.full(len(rots), max_angle)
            for _ in range(7):  # bisection on the angle, all frames at once
                mid = 0.5 * (lo + hi)
                ok = distances(rotated(rots, b, Xp, axis, sign * mid), arm) >= clearance
                hi = np.where(ok, mid, hi)
                lo = np.where(ok, lo, mid)
            theta = np.where(need, hi, 0.0)
            # no jitter: hold the largest angle for a third of a second around each frame, then smooth
            w = max(1, int(round(m.fps / 3)))
            theta = gaussian_filter1d(maximum_filter1d(theta, size=2 * w + 1), sigma=w / 2)
            rots = rotated(rots, b, Xp, axis, sign * theta)
        info[side] = {"distance_before_m": d0, "distance_after_m": distances(rots, arm), "angle_rad": theta}
    return Motion(m.name, m.fps, m.bone_names, rots, trs), info
