"""Retarget a skeleton animation (a BVH file, an AMASS/SMPL motion) onto Anny.

The source is a skeleton with, per frame, each joint's global rotation ``G_j(t)`` relative to the
skeleton's zero pose (all channels zero) and its position ``P_j(t)``, in the file's axes and units.
A :class:`~physavatar.body.skeleton_map.SkeletonMap` says which joint drives which Anny bone.

1. Calibration pose: the zero pose when it stands (legs below the hips, the head above, hips
   apart: T-pose, A-pose, arms hanging), else the first frame (files whose zero pose has every
   bone along a local axis). Axes ``C`` come from it: up = hips → head (snapped to the nearest
   axis within 20°, or given: AMASS is z-up), left = right hip → left hip; Anny is z-up, facing −y,
   left at +x, so ``C`` turns the file's axes into Anny's.
2. Alignment ``A_b``: the rotation that takes Anny's rest pose to the calibration pose, bone by
   bone from the root outwards: each mapped bone (but the pelvis sides, root → hip joints,
   which keep Anny's hips: ``_RIGID``, and the collars: ``_COLLAR``) is turned (after its
   parent's turn) so that its segment to the next mapped joint points as in the file (the
   longest such segment exactly, the others by the best twist about it; a leaf uses the joint's
   child or BVH end site against the bone's own axis, or the direction to Anny's toes or middle
   knuckle for feet and hands).
3. Frames: ``X_b(t) = C G_j(t) G_j(cal)ᵀ Cᵀ A_b``: the file's rotation since the calibration pose,
   applied to Anny's calibrated bone; for a collar ``G_j(cal)`` is its parent's calibration
   rotation times the collar's average local rotation over the clip (Anny's rest collar stands for
   the file's average one). Unmapped Anny bones follow their parent. Local rotations
   ``X_parentᵀ X_b`` are stored as axis-angle (docs/motions.md).
4. Root translation: the hips' path times ``scale`` (Anny's hip-to-ankle length over the file's:
   units and body size at once), horizontally relative to the first frame; vertically so that
   Anny's lowest ankle over the whole clip is at its rest height (the feet on the floor when the
   file's are lowest), following the file's hips up and down.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import PhysavatarError
from .model import BodyModel, axis_angle_to_matrix, matrix_to_axis_angle
from .motion import Motion
from .skeleton_map import SkeletonMap


@dataclass
class SourceMotion:
    """A skeleton animation in its own axes and units.

    Attributes:
        names, parents: [J] joint names and parent indices (-1: a root).
        rest: [J, 3] joint positions in the zero pose.
        G: [T, J, 3, 3] global joint rotations relative to the zero pose.
        P: [T, J, 3] joint positions.
        fps: frames per second.
        tips: joint -> a tip vector in the joint's zero-pose frame (BVH end sites).
        up: the world's up axis when known, else None (found from the skeleton).
        axes: the rotation from the file's axes to Anny's when known (AMASS: the world's own
            heading is kept), else None (found from the calibration pose).
    """

    names: list[str]
    parents: np.ndarray
    rest: np.ndarray
    G: np.ndarray
    P: np.ndarray
    fps: float
    tips: dict = field(default_factory=dict)
    up: np.ndarray | None = None
    axes: np.ndarray | None = None


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction a onto direction b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    s, c = np.linalg.norm(v), float(np.dot(a, b))
    if s < 1e-9:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        return axis_angle_to_matrix(np.pi * perp / np.linalg.norm(perp))
    return axis_angle_to_matrix(v / s * np.arctan2(s, c))


def _align(pairs: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Rotation taking each a onto its d: the longest pair exactly, then the twist about it that
    best matches the others (weighted by their lengths across the axis)."""
    pairs = sorted(pairs, key=lambda p: -np.linalg.norm(p[0]))
    a0, d0 = pairs[0]
    R = rotation_between(a0, d0)
    axis = d0 / np.linalg.norm(d0)
    sn = cs = 0.0
    for a, d in pairs[1:]:
        u = R @ a
        u = u - np.dot(u, axis) * axis
        v = d - np.dot(d, axis) * axis
        w = np.linalg.norm(u) * np.linalg.norm(v)
        if w < 1e-12:
            continue
        ang = np.arctan2(np.dot(axis, np.cross(u, v)), np.dot(u, v))
        sn += w * np.sin(ang)
        cs += w * np.cos(ang)
    if sn or cs:
        R = axis_angle_to_matrix(axis * np.arctan2(sn, cs)) @ R
    return R


def _unit(v):
    n = np.linalg.norm(v)
    return v / n if n > 0 else v


def _snap(v, deg=20.0):
    ax = np.eye(3)[np.argmax(np.abs(v))] * np.sign(v[np.argmax(np.abs(v))])
    return ax if np.dot(_unit(v), ax) > np.cos(np.radians(deg)) else _unit(v)


# Anny bones that are part of the rigid hips: the pelvis sides (root -> hip joint). No pose turns
# them against the root, so their direction in a file's calibration pose says only where that
# skeleton puts its root joint: CMU's LHipJoint runs 50 deg down and forwards from a root at the
# hip joints' height, Anny's pelvis.L sideways. Aimed at the file's hip joints, they swung Anny's
# hip joints 8 cm down and together (CMU 131_01: 0.204 -> 0.115 m apart, the thighs through each
# other in most frames). They keep Anny's rest direction (the file's motion since the calibration
# pose is still applied to them).
# The collar bones are not aimed either: their direction says where a skeleton puts its collar
# joint (CMU: at the neck base, the shoulder 26 deg above it; Anny: beside the sternum, 10 deg
# down) as much as a pose, and aimed they shrugged Anny's shoulders 8-10 cm on the CMU clips. But
# a zero pose's collars can also be a pose (SMPL's T-pose raises them; a relaxed AMASS actor's
# turn down from it, and kept at Anny's rest against the zero pose they sank 28 deg: AMASS round
# trip 3.7 cm). So a collar keeps Anny's rest direction in the file's *average* collar pose over
# the clip (relative to its parent), and the motion is taken from there: collars move little and
# come back. The arms are aimed as before (the arm's direction is matched; only the shoulder
# joint's place on the chest is Anny's).
_RIGID = ("pelvis.",)
_COLLAR = ("clavicle.",)


def _mean_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation nearest the average of rotation matrices [T, 3, 3] (chordal mean)."""
    U, _, Vt = np.linalg.svd(R.mean(0))
    if np.linalg.det(U @ Vt) < 0:
        U[:, -1] *= -1
    return U @ Vt


def _leg_joints(by: dict[str, int], side: str) -> list[int]:
    return [by[b] for b in (f"upperleg01.{side}", f"lowerleg01.{side}", f"foot.{side}") if b in by]


def check_map(sm: SkeletonMap, body: BodyModel, path) -> None:
    """One clear error when the hips or a leg cannot be found, or a bone name is not Anny's."""
    bad = sorted({v for v in sm.bones.values() if v not in body.bone_names})
    if bad:
        raise PhysavatarError(path, f"joint mapping names unknown Anny bones {bad}")
    by = sm.by_bone
    if "root" not in by:
        raise PhysavatarError(path, "cannot find the hips: no joint is named like Hips/Pelvis and no joint has "
                              "both legs below it (map one to 'root' with --mapping)")
    for side, word in (("L", "left"), ("R", "right")):
        if len(_leg_joints(by, side)) < 2:
            found = [sm.names[j] for j in _leg_joints(by, side)]
            raise PhysavatarError(path, f"cannot find the {word} leg (upper leg and knee or ankle; found "
                                  f"{found or 'none'}); name the joints like LeftUpLeg/LeftLeg/LeftFoot or give --mapping")
    if not any(b in by for b in ("head", "neck01", "spine01")):
        raise PhysavatarError(path, "cannot find the spine, neck or head above the hips (give --mapping)")


def _frame_axes(P0, by, up_hint):
    """(C, ok): C turns file axes into Anny's (rows: Anny x, y, z in file axes); ok: the pose stands."""
    hips = P0[by["root"]]
    top = P0[next(by[b] for b in ("head", "neck03", "neck02", "neck01", "spine01") if b in by)]
    feet = np.mean([P0[_leg_joints(by, s)[-1]] for s in "LR"], axis=0)
    up, down = top - hips, feet - hips
    left = P0[by["upperleg01.L"]] - P0[by["upperleg01.R"]]
    if np.linalg.norm(left) < 1e-9 * (1 + np.linalg.norm(down)):
        left = P0[_leg_joints(by, "L")[1]] - P0[_leg_joints(by, "R")[1]]
    stands = np.dot(_unit(up), _unit(down)) < -0.7
    u = _unit(np.asarray(up_hint, float)) if up_hint is not None else _snap(up)
    lp = left - np.dot(left, u) * u
    stands = stands and np.linalg.norm(lp) > 0.05 * np.linalg.norm(down)
    if np.linalg.norm(lp) < 1e-12:
        return None, False
    lp = _unit(lp)
    fwd = np.cross(lp, u)
    return np.stack([lp, -fwd, u]), bool(stands)


def _anny_leaf(body: BodyModel, b: int) -> np.ndarray:
    """Direction of Anny bone b's far end: its toes or middle knuckle for feet and hands, else its axis."""
    names, R = body.bone_names, body.rest_joints
    n = names[b]
    side = n[-2:] if n.endswith((".L", ".R")) else ""
    if n.startswith("foot") and f"toe3-1{side}" in names:
        return np.mean([R[names.index(f"toe{k}-1{side}")] for k in range(1, 6)], axis=0) - R[b]
    if n.startswith("wrist") and f"finger3-1{side}" in names:
        return R[names.index(f"finger3-1{side}")] - R[b]
    return body.rest_bone_axes[b][:, 1] * 0.1


def retarget(src: SourceMotion, body: BodyModel, sm: SkeletonMap, *, path=None, name: str = "motion",
             meta: dict | None = None) -> Motion:
    """Anny motion following ``src`` through the joint map ``sm`` (see module doc)."""
    check_map(sm, body, path)
    by = sm.by_bone
    T, J = src.G.shape[:2]
    calib = None
    for label, G0, P0 in (("the zero pose", np.broadcast_to(np.eye(3), (J, 3, 3)), src.rest),
                          ("the first frame", src.G[0], src.P[0])):
        C, ok = _frame_axes(P0, by, src.up)
        if ok:
            C = C if src.axes is None else np.asarray(src.axes, float)
            calib = (label, np.asarray(G0), np.asarray(P0), C)
            break
    if calib is None:
        raise PhysavatarError(path, "neither the zero pose nor the first frame stands upright (legs below the "
                              "hips, head above, hips apart): cannot tell the file's axes")
    label, G0, P0, C = calib

    anny = body.rest_joints
    names = body.bone_names
    aidx = {n: i for i, n in enumerate(names)}
    par = body.parents
    B = len(names)

    def leg_len(P, idx):
        return float(sum(np.linalg.norm(P[a] - P[b]) for a, b in zip(idx, idx[1:])))

    src_leg = np.mean([leg_len(src.P[0], _leg_joints(by, s)) for s in "LR"])
    anny_leg = np.mean([leg_len(anny, [aidx[sm.bones[j]] for j in _leg_joints(by, s)]) for s in "LR"])
    if not src_leg > 0:
        raise PhysavatarError(path, "the legs have zero length")
    scale = float(anny_leg / src_leg)

    Q = P0 @ C.T  # calibration positions in Anny axes (file units)
    eps = 1e-3 * src_leg
    mapped = {aidx[bone]: j for j, bone in sm.bones.items()}
    akids = {b: [c for c in range(B) if par[c] == b] for b in range(B)}
    skids = {j: [k for k in range(J) if src.parents[k] == j] for j in range(J)}
    A = np.empty((B, 3, 3))
    for b in range(B):  # parents first
        Ap = A[par[b]] if par[b] >= 0 else np.eye(3)
        if b not in mapped or names[b].startswith(_RIGID + _COLLAR):
            A[b] = Ap
            continue
        j = mapped[b]
        pairs, stack = [], list(akids[b])
        while stack:
            c = stack.pop(0)
            if c in mapped:
                a, d = anny[c] - anny[b], Q[mapped[c]] - Q[j]
                if np.linalg.norm(a) > 1e-4 and np.linalg.norm(d) > eps:
                    pairs.append((Ap @ a, d))
                    continue
            stack.extend(akids[c])
        if not pairs:  # a leaf: its child joint or end site against the bone's own far end
            tip, frontier = None, list(skids[j])
            while frontier and tip is None:
                nz = [k for k in frontier if k not in sm.bones and np.linalg.norm(Q[k] - Q[j]) > eps]
                if nz:
                    tip = Q[nz[0]] - Q[j]
                frontier = [c for k in frontier if k not in sm.bones for c in skids[k]]
            if tip is None and j in src.tips and np.linalg.norm(src.tips[j]) > 0:
                tip = C @ G0[j] @ src.tips[j]
            leaf = Ap @ _anny_leaf(body, b)
            pj = src.parents[j]
            if tip is not None and pj >= 0 and par[b] >= 0 and np.linalg.norm(Q[j] - Q[pj]) > eps:
                # a tip continuing the bone above it where Anny's bends away (a foot without a
                # toe: an end site straight down the shin) says nothing about the leaf: keep it as is
                bend_anny = np.dot(_unit(leaf), _unit(Ap @ (anny[b] - anny[par[b]])))
                bend_src = np.dot(_unit(tip), _unit(Q[j] - Q[pj]))
                if bend_anny < np.cos(np.radians(45)) and bend_src > np.cos(np.radians(30)):
                    tip = None
            if tip is not None:
                pairs = [(leaf, tip)]
        A[b] = (_align(pairs) @ Ap) if pairs else Ap

    X = np.empty((T, B, 3, 3))
    for b in range(B):
        if b in mapped:
            j = mapped[b]
            G0j = G0[j]
            pj = src.parents[j]
            if names[b].startswith(_COLLAR) and pj >= 0:  # calibrated on the clip's average collar pose
                G0j = G0[pj] @ _mean_rotation(np.swapaxes(src.G[:, pj], -1, -2) @ src.G[:, j])
            X[:, b] = C @ src.G[:, j] @ G0j.T @ C.T @ A[b]
        else:
            X[:, b] = X[:, par[b]] if par[b] >= 0 else np.eye(3)
    D = X.copy()
    for b in range(1, B):
        D[:, b] = np.swapaxes(X[:, par[b]], -1, -2) @ X[:, b]
    rot = matrix_to_axis_angle(D.reshape(-1, 3, 3)).reshape(T, B, 3)

    hips = (src.P[:, by["root"]] @ C.T) * scale
    tr = hips - hips[0]
    heads = body.world_bone_poses(rot, np.zeros((T, 3)))[:, :, 2, 3] + body.floor_offset
    feet = [aidx[sm.bones[_leg_joints(by, s)[-1]]] for s in "LR"]
    lowest = float(min((heads[:, f] + tr[:, 2]).min() for f in feet))
    tr[:, 2] += min(anny[f, 2] for f in feet) - lowest
    meta = dict(meta or {})
    meta.update({"scale_m_per_unit": scale, "calibration": label, "axes": C.tolist(),
                 "mapped_joints": {sm.names[j]: v for j, v in sm.bones.items()},
                 "mapping_why": {sm.names[j]: w for j, w in sm.why.items()}})
    return Motion(name, src.fps, names, rot, tr, meta)
