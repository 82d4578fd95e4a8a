"""Room between the body parts a garment covers: a motion correction for motion capture.

Motion capture retargeted onto Anny often makes the collider pass through itself: a hand rests in
the hip, the forearm swings through the thigh, the thigh of a high step sinks centimetres into the
belly (linear blend skinning collapses the groin). A garment lying between two such parts has no
position outside the body at all: a contact-exact simulator lags or leaves cloth inside the body
there (docs/simulation.md, "Session 21" and "Session 23"). The given motion is physically
impossible in those frames, so it is changed, as little as the rule below needs, and the change is
reported.

:func:`part_clearance` applies :class:`Clearance` rules. A rule names a joint (the head of a bone),
the *part* it moves (the vertices whose dominant bone has one of the given prefixes) and an
*obstacle* (another set of vertices and the triangles among them). In every frame where a point of
the part comes closer than ``clearance`` to the obstacle's surface, the bone is turned at its joint
about the axis that moves that closest point straight away from the obstacle (the axis
``(p - joint) x n``, n the obstacle's normal at the closest point), by the smallest angle (a
bisection) that clears it, at most ``max_angle``. The angles are held over a third of a second and
smoothed over time (no jitter), and the measure-turn-smooth round is repeated for the frames still
short (``rounds``), the total turn bounded by ``max_angle``. Frames where no point comes too close,
and that no smoothing window reaches, are left exactly as they are.

A ``collapse`` rule measures instead how deep a vertex of the part lies inside the obstacle or one
of the obstacle inside the part, the joint's own fold included (the body's winding number, as
``sim.crease`` finds buried vertices; the depth below the outer surface), and opens the joint,
turning the bone about the normal of its own and its parent's direction, until none is buried
(clearance 0). Linear blend skinning folds the back of a deeply bent knee into the limb: the
cloth caught in that fold has no place outside the body (docs/simulation.md "Session 28").

A collapse rule with ``min_depth`` > 0 opens the joint only where the parts pass through each other
deeper than that, decided from the motion before it is changed (:func:`collapse_windows`): the
frames with a buried vertex, joined into windows where the rule's smoothing of one would reach the
other (about 1 s); per
frame, the crossing's depth is the smallest hinge opening that clears the frame (a bisection to
0.006 degrees) times the largest distance of a buried vertex from the hinge's axis (how far the
surface there has to move to come apart); a window whose deepest frame is shallower than
``min_depth`` is left exactly as it is (its frames never count as needing a turn, and no other
window's turn reaches them); the other windows
are opened as without ``min_depth``. ``knee_collapse_rules(KNEE_ROOM)``: the knee opened only where
the crossing is deeper than the room the cloth's contact needs, ``--knee-collapse`` auto
(docs/simulation.md "Session 33").

Parts connected at the joint (the thigh and the belly at the hip) are always in contact near the
joint; ``rest_gap`` leaves out the points of the part and the obstacle that are closer than that to
each other in the rest pose: the rule then keeps apart only what is apart at rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import BodyModel, bone_vertex_mask
from .motion import Motion, turn_bone, world_rotations


@dataclass(frozen=True)
class Clearance:
    """One part kept ``clearance`` [m] away from an obstacle by turning ``joint`` (a bone name)
    at most ``max_angle`` [rad]; pairs closer than ``rest_gap`` [m] at rest are left out."""

    name: str
    joint: str
    part: tuple[str, ...]
    obstacle: tuple[str, ...]
    clearance: float
    max_angle: float
    rest_gap: float = 0.0
    exclude: tuple[str, ...] = ()  # bones left out of the obstacle on the joint's side (the limb itself)
    collapse: bool = False  # measure the collapse instead: the joint opened until no vertex is buried
    min_depth: float = 0.0  # a collapse rule: windows of frames crossing less deep than this [m] left as they are


_HAND = ("lowerarm", "wrist", "hand", "finger", "thumb", "metacarpal")
_TRUNK = ("root", "pelvis", "spine")
_ARM = ("clavicle", "shoulder", "upperarm") + _HAND


def default_rules(clearance: float = 0.03) -> list[Clearance]:
    """The rules :func:`part_clearance` applies by default, meant for motion capture after
    ``motion.arm_clearance`` (``simulate`` / ``animate --part-clearance``, off by default;
    ``benchmarks/motion_suite.py --part-clearance``): the thigh out
    of the belly (at most 35 degrees of hip flexion taken back; pairs within 6 cm of each other at
    rest, the groin, left out), the calf out of the thigh at the back of the knee (the same bounds
    for the knee), then the forearm and hand off every other part of the body (at most 40 degrees
    more at the shoulder, on top of ``arm_clearance``'s sideways raise). The knee's collapse:
    :func:`knee_collapse_rules`, applied after these by ``body.load.with_part_clearance``."""
    rules = []
    for s in ("L", "R"):
        rules.append(Clearance(f"thigh-belly.{s}", f"upperleg01.{s}", (f"upperleg01.{s}", f"upperleg02.{s}"), _TRUNK,
                               clearance=0.01, max_angle=np.radians(35.0), rest_gap=0.06))
    for s in ("L", "R"):
        rules.append(Clearance(f"knee-fold.{s}", f"lowerleg01.{s}", (f"lowerleg01.{s}", f"lowerleg02.{s}"), ("upperleg",),
                               clearance=0.01, max_angle=np.radians(20.0), rest_gap=0.06))
    for s in ("L", "R"):
        rules.append(Clearance(f"hand-body.{s}", f"upperarm01.{s}", _HAND, ("",), clearance=clearance,
                               max_angle=np.radians(40.0), exclude=_ARM))
    return rules


KNEE_ROOM = 1e-3  # [m] the room the cloth's contact needs: d̂ (sim.settings.SimSettings.dhat) + the
# cotton preset's contact offset (0); the stages pass their own d̂ + offset


def knee_collapse_rules(min_depth: float = 0.0) -> list[Clearance]:
    """The knee opened where calf and thigh pass through each other at the back of the knee (at
    most 25 degrees; ``collapse``: the fold the knee-fold rule leaves out with its ``rest_gap``).
    Not in :func:`default_rules`: on the 2-cm hop it takes out the pinch of written frames 164-166,
    on the CMU walk its turns of under 1 degree leave cloth in the knee pit at written 80-83
    (docs/simulation.md "Session 29"). ``min_depth`` [m]: only windows of frames where they cross
    deeper than this are opened (``--knee-collapse`` auto: :data:`KNEE_ROOM`; "Session 33"). Meant
    after the default rules (a clip they corrected needs only these on top)."""
    return [Clearance(f"knee-collapse.{s}", f"lowerleg01.{s}", (f"lowerleg01.{s}", f"lowerleg02.{s}"), ("upperleg",),
                      clearance=0.0, max_angle=np.radians(25.0), collapse=True, min_depth=min_depth)
            for s in ("L", "R")]


BURIED = 1.0  # winding number above which a vertex lies inside another part (as sim.crease.BURIED;
# a vertex on its own surface reads ~0.5)


def _side_mask(body: BodyModel, prefixes, side: str | None) -> np.ndarray:
    names = [n for n in body.bone_names if n.startswith(tuple(prefixes))
             and (side is None or n.endswith(f".{side}") or not n.endswith((".L", ".R")))]
    return bone_vertex_mask(body, names)


class _Geometry:
    """The part's vertices and the obstacle's surface samples (with normals) of one rule."""

    def __init__(self, body: BodyModel, rule: Clearance, samples_per_face: int):
        from scipy.spatial import cKDTree

        side = rule.joint.rsplit(".", 1)[1] if rule.joint.endswith((".L", ".R")) else None
        part = _side_mask(body, rule.part, side)
        # the obstacle: both sides' parts (a hand meets either thigh), never the part itself
        obst = bone_vertex_mask(body, [n for n in body.bone_names if n.startswith(tuple(rule.obstacle))]) & ~part
        if rule.exclude:
            obst &= ~_side_mask(body, rule.exclude, side)
        R = np.asarray(body.rest_vertices)
        F = np.asarray(body.faces)
        # a collapse rule: the part and the obstacle on its side, joint included
        self.sides = part, obst & _side_mask(body, rule.obstacle, side)
        self.near, self.all_faces = np.flatnonzero(part | self.sides[1]), F
        if rule.rest_gap > 0 and part.any() and obst.any():
            d_part = cKDTree(R[obst]).query(R)[0]
            d_obst = cKDTree(R[part]).query(R)[0]
            part &= d_part > rule.rest_gap
            obst &= d_obst > rule.rest_gap
        self.part = np.flatnonzero(part)
        self.faces = F[np.all(obst[F], axis=1)]
        self.bary = np.random.default_rng(0).dirichlet([1.0, 1.0, 1.0], size=(len(self.faces), samples_per_face))

    def closest(self, V):
        """Per frame of V [T, N, 3]: (distance [T], part point [T, 3], obstacle normal [T, 3])."""
        from scipy.spatial import cKDTree

        T = len(V)
        d, p, n = np.empty(T), np.empty((T, 3)), np.empty((T, 3))
        for t in range(T):
            tri = V[t][self.faces]
            P = np.einsum("fsk,fkd->fsd", self.bary, tri).reshape(-1, 3)
            nf = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            dd, j = cKDTree(P).query(V[t][self.part])
            i = int(np.argmin(dd))
            d[t], p[t] = dd[i], V[t][self.part[i]]
            nn = nf[j[i] // self.bary.shape[1]]
            n[t] = nn / max(np.linalg.norm(nn), 1e-12)
        return d, p, n


    def buried_depth(self, V, buried=None):
        """Per frame of V [T, N, 3]: minus the depth [m] of the deepest vertex of the part buried in
        the obstacle or of the obstacle buried in the part (winding number of the body above
        BURIED; the closest triangle of the body's outer surface, its triangles more than one ring
        from a buried vertex, has a corner on the other side), 0 where none is. ``buried``: a list
        that gets, per frame, those vertices (indices)."""
        from ..geometry.closest import MeshQuery
        from ..geometry.winding import winding_number

        F, out = self.all_faces, np.zeros(len(V))
        for t in range(len(V)):
            bur = self.near[winding_number(V[t][self.near], V[t], F, self.near) > BURIED]
            if buried is not None:
                buried.append(bur[:0])
            if not len(bur):
                continue
            hidden = np.zeros(len(V[t]), bool)
            hidden[bur] = True
            hidden[F[hidden[F].any(axis=1)].ravel()] = True
            outer = F[~hidden[F].any(axis=1)]
            depth, face, _, _ = MeshQuery(V[t], outer, spacing=0.02).closest(V[t][bur])
            part, obst = self.sides
            across = np.where(part[bur], obst[outer[face]].any(axis=1), part[outer[face]].any(axis=1))
            if across.any():
                out[t] = -float(np.max(depth[across]))
                if buried is not None:
                    buried[-1] = bur[across]
        return out


def _opening_axis(joints, b, parent, child):
    """Per frame, the world axis about which a positive turn of bone ``b`` straightens its joint
    (turns the bone's direction towards its parent's)."""
    u = joints[:, b] - joints[:, parent]
    w = joints[:, child] - joints[:, b]
    a = np.cross(w, u)
    return a / np.maximum(np.linalg.norm(a, axis=1), 1e-12)[:, None]


def _smooth(theta, axis, fps):
    """Angles held for a third of a second around each frame and smoothed; the axis smoothed
    with them (the angle-weighted mean of the frames' axes nearby)."""
    from scipy.ndimage import gaussian_filter1d, maximum_filter1d

    w = max(1, int(round(fps / 3)))
    held = gaussian_filter1d(maximum_filter1d(theta, size=2 * w + 1), sigma=w / 2)
    vec = gaussian_filter1d(axis * theta[:, None], sigma=2 * w, axis=0, mode="nearest")
    norm = np.linalg.norm(vec, axis=1)
    held[norm < 1e-12] = 0.0
    return held[:, None] * vec / np.maximum(norm, 1e-12)[:, None]


def collapse_windows(body: BodyModel, rots, trs, rule: Clearance, fps: float, samples_per_face: int = 10,
                     iterations: int = 12) -> list[dict]:
    """Where collapse rule ``rule`` finds the part and the obstacle passing through each other in
    the motion ``rots`` [T, B, 3], ``trs`` [T, 3]: the frames with a buried vertex, in windows
    (frames within the reach of the rule's smoothing of each other joined: 3 holds of ⅓ s, the
    held maximum and the Gaussian's 4 sigma, so that no opened window's turn reaches a left one). Per
    frame: ``opening_rad``, the smallest turn of the joint about its hinge axis that leaves no
    vertex buried (bisection, ``iterations`` halvings of ``max_angle``: 0.006 degrees), and
    ``depth_m``, that opening times the largest distance of a buried vertex from the hinge's axis
    through the joint (how far the surface there has to move to come apart; the arc, not the
    chord: they differ by under 0.1 % below 5 degrees). ``opened``: the window's deepest frame is
    at least ``rule.min_depth`` deep."""
    idx = {n: i for i, n in enumerate(body.bone_names)}
    b, parents = idx[rule.joint], body.parents
    child = next(i for i, q in enumerate(parents) if q == b)
    g = _Geometry(body, rule, samples_per_face)
    buried: list = []
    frames = np.flatnonzero(g.buried_depth(body.pose(rots, trs).vertices, buried) < 0)
    if not len(frames):
        return []
    P = body.pose(rots[frames], trs[frames])
    axis = _opening_axis(P.joints, b, parents[b], child)
    Xp = world_rotations(rots[frames], parents)[:, parents[b]]
    lo, hi = np.zeros(len(frames)), np.full(len(frames), rule.max_angle)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        turned = turn_bone(rots, b, Xp, axis * mid[:, None], frames)[frames]
        ok = g.buried_depth(body.pose(turned, trs[frames]).vertices) >= 0
        hi, lo = np.where(ok, mid, hi), np.where(ok, lo, mid)
    reach = np.empty(len(frames))
    for k, t in enumerate(frames):
        r = P.vertices[k][buried[t]] - P.joints[k, b]
        reach[k] = np.linalg.norm(r - np.outer(r @ axis[k], axis[k]), axis=1).max()
    hold = max(1, int(round(fps / 3)))
    out = []
    for grp in np.split(np.arange(len(frames)), np.flatnonzero(np.diff(frames) > 3 * hold) + 1):
        depth = hi[grp] * reach[grp]
        out.append({"frames": frames[grp], "opening_rad": hi[grp], "depth_m": depth,
                    "opened": bool(depth.max() >= rule.min_depth)})
    return out


def part_clearance(motion, body: BodyModel, rules=None, samples_per_face: int = 10, rounds: int = 3):
    """The motion with every rule of ``rules`` (default :func:`default_rules`) applied in turn.
    Returns (motion, info): per rule, the distance before and after [T] and the angle added [T]
    (radians); a collapse rule with ``min_depth``: also its ``windows`` (:func:`collapse_windows`)."""
    rules = default_rules() if rules is None else rules
    m = motion.for_bones(body.bone_names)
    rots, trs = m.rotations.copy(), m.root_translation
    idx = {n: i for i, n in enumerate(body.bone_names)}
    parents = body.parents
    info = {}
    for rule in rules:
        b = idx.get(rule.joint)
        if b is None:
            continue
        g = _Geometry(body, rule, samples_per_face)
        if not len(g.part) or not len(g.faces):
            continue

        def measure(r, frames):
            P = body.pose(r[frames], trs[frames])
            if rule.collapse:
                return g.buried_depth(P.vertices), None, None, P.joints
            return g.closest(P.vertices) + (P.joints,)

        child = next((i for i, q in enumerate(parents) if q == b), None)
        if rule.collapse and child is None:
            continue
        T = len(rots)
        d0 = measure(rots, np.arange(T))[0]
        left, windows = np.zeros(T, bool), None  # frames of windows too shallow to open
        if rule.collapse and rule.min_depth > 0:
            windows = collapse_windows(body, rots, trs, rule, m.fps, samples_per_face)
            for w in windows:
                left[w["frames"]] |= not w["opened"]
        total = np.zeros((T, 3))
        for _ in range(rounds):
            d, p, n, joint = measure(rots, np.arange(T))
            budget = rule.max_angle - np.linalg.norm(total, axis=1)
            need = np.flatnonzero((d < rule.clearance) & (budget > 1e-3) & ~left)
            if not len(need):
                break
            if rule.collapse:
                axis = _opening_axis(joint[need], b, parents[b], child)
            else:
                axis = np.cross(p[need] - joint[need, b], n[need])
                axis /= np.maximum(np.linalg.norm(axis, axis=1), 1e-12)[:, None]
            Xp = world_rotations(rots[need], parents)[:, parents[b]]
            lo, hi = np.zeros(len(need)), budget[need].copy()
            for _ in range(7):  # bisection on the angle, all frames at once
                mid = 0.5 * (lo + hi)
                ok = measure(turn_bone(rots, b, Xp, axis * mid[:, None], need), need)[0] >= rule.clearance
                hi, lo = np.where(ok, mid, hi), np.where(ok, lo, mid)
            # where no angle within the budget clears it, the angle (of five) that leaves the most room
            short = measure(turn_bone(rots, b, Xp, axis * hi[:, None], need), need)[0] < rule.clearance
            if short.any():
                grid = np.linspace(0.0, 1.0, 5)
                best = np.stack([measure(turn_bone(rots, b, Xp, axis * (a * budget[need])[:, None], need), need)[0]
                                 for a in grid])
                hi = np.where(short, grid[np.argmax(best, axis=0)] * budget[need], hi)
            theta, ax = np.zeros(T), np.zeros((T, 3))
            theta[need], ax[need] = hi, axis
            vec = _smooth(theta, ax, m.fps)
            # the total stays within max_angle
            tot = total + vec
            over = np.linalg.norm(tot, axis=1) / rule.max_angle
            vec = np.where(over[:, None] > 1, tot / np.maximum(over, 1)[:, None] - total, vec)
            moved = np.flatnonzero(np.linalg.norm(vec, axis=1) > 0)
            if not len(moved):
                break
            Xp = world_rotations(rots[moved], parents)[:, parents[b]]
            rots = turn_bone(rots, b, Xp, vec[moved], moved)
            total += vec
        info[rule.name] = {"distance_before_m": d0, "distance_after_m": measure(rots, np.arange(T))[0],
                           "angle_rad": np.linalg.norm(total, axis=1)}
        if windows is not None:
            info[rule.name]["windows"] = windows
    return Motion(m.name, m.fps, m.bone_names, rots, trs, dict(m.meta)), info
