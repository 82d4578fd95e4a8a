"""A garment's openings (neck, waist, hem, sleeves, trouser legs) and the limb pose they ask for.

A garment made on another body is draped there with that body's limbs posed its own way: a
T-shirt's sleeves stand out nearly horizontally, a dress's armholes face sideways, trouser legs
hang closer together than Anny's legs. Before the garment can settle on a body that grows inside
it, the body's limbs must run along the garment's sleeves and legs (garment.fit).

:func:`find_openings` finds the open boundary loops of the sewn garment (panels welded along
their seams: an edge of one triangle only) and names them by where they are on the garment
(z up). A loop around the garment's vertical axis (its centre closer to the axis than its
radius) is central: the highest is the ``neck`` when the garment has arm openings, else the
``waist``, the lowest in the lower half the ``hem``. The other loops are at the sides: two in the
upper half of the garment's height are ``arm`` openings (sleeve cuffs, whether the sleeves point
down or up, or armholes), two in the lower half ``leg`` openings (trouser cuffs). The pair gives
the garment's lateral axis (left-right), which the alignment turns onto the body's x axis.

:func:`limb_pose` gives the pose rotations that put each arm and leg of the body through its
opening: the arm, its elbow straightened, rotated about the shoulder joint so that it points
at the centre of its opening (a sleeve cuff), or, when the opening is an armhole around the
shoulder joint itself (closer than 1.5 of its radius), along the opening's outward normal; the
leg rotated about the hip joint so that it points at the centre of its trouser cuff, and for a
cuff at the ankle the foot pointed down along the leg (a foot is longer than a cuff is wide).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ARM_ROOT, LEG_ROOT = "upperarm01", "upperleg01"
ARM_END, LEG_END = "lowerarm01", "foot"  # the rest direction of a limb: root joint to this joint
FOOT, WRIST = "foot", "wrist"


@dataclass(eq=False)
class Opening:
    """An open boundary loop of a garment.

    Attributes:
        kind: "neck", "waist", "hem", "arm", "leg" or "other".
        centre: [3] mean of the loop's vertices. normal: [3] unit normal of the loop's best-fit
            plane, pointing out of the garment. radius: mean distance of the loop to its centre.
        vertices: [K] garment vertex ids on the loop (one per sewn point).
    """

    kind: str
    centre: np.ndarray
    normal: np.ndarray
    radius: float
    vertices: np.ndarray

    def moved(self, R: np.ndarray, t: np.ndarray, about: np.ndarray, scale: float = 1.0) -> "Opening":
        """The opening after the garment moved: x → about + scale R (x − about) + t."""
        return Opening(self.kind, about + scale * R @ (self.centre - about) + t, R @ self.normal,
                       self.radius * scale, self.vertices)


def sewn_ids(n: int, seams) -> np.ndarray:
    """[n] one id per sewn point: the vertices a seam joins share it (connected components)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    seams = np.zeros((0, 2), np.int64) if seams is None else np.asarray(seams, np.int64).reshape(-1, 2)
    A = sp.coo_matrix((np.ones(len(seams)), (seams[:, 0], seams[:, 1])), shape=(n, n))
    return connected_components(A, directed=False)[1]


def boundary_loops(vertices, faces, seams=None) -> list[np.ndarray]:
    """The open boundary loops of the garment sewn along ``seams``: per loop, the garment vertex
    ids on it (the first panel vertex of every sewn point)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = len(vertices)
    lab = sewn_ids(n, seams)
    F = lab[np.asarray(faces, np.int64)]
    E = np.sort(np.vstack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    E = E[E[:, 0] != E[:, 1]]
    u, c = np.unique(E, axis=0, return_counts=True)
    be = u[c == 1]
    if not len(be):
        return []
    m = lab.max() + 1
    A = sp.coo_matrix((np.ones(len(be)), (be[:, 0], be[:, 1])), shape=(m, m))
    _, comp = connected_components(A, directed=False)
    first = np.full(m, -1)
    first[lab[::-1]] = np.arange(n)[::-1]  # the first panel vertex of every sewn point
    used = np.unique(be)
    return [first[used[comp[used] == k]] for k in np.unique(comp[used])]


def _loop(V, ids, inside):
    P = V[ids]
    c = P.mean(0)
    n = np.linalg.svd(P - c, full_matrices=False)[2][2]
    if np.dot(n, c - inside) < 0:
        n = -n
    return c, n, float(np.linalg.norm(P - c, axis=1).mean())


def find_openings(vertices, faces, seams=None, min_loop: int = 6) -> list[Opening]:
    """The garment's openings, named (module docstring); loops of fewer than ``min_loop``
    vertices (a slit, a hole left by a bad seam) are "other"."""
    V = np.asarray(vertices, np.float64)
    inside = V.mean(0)
    loops = [ids for ids in boundary_loops(V, faces, seams)]
    ops = []
    for ids in loops:
        c, n, r = _loop(V, ids, inside)
        ops.append(Opening("other", c, n, r, ids))
    real = [o for o in ops if len(o.vertices) >= min_loop]
    if not real:
        return ops
    zlo, zhi = V[:, 2].min(), V[:, 2].max()
    mid = V[:, :2].mean(0)
    central = [o for o in real if np.linalg.norm(o.centre[:2] - mid) < o.radius]  # around the garment's axis
    side = [o for o in real if all(o is not q for q in central)]
    upper = [o for o in side if o.centre[2] >= zlo + 0.5 * (zhi - zlo)]
    lower = [o for o in side if all(o is not q for q in upper)]
    if len(upper) == 2:
        for o in upper:
            o.kind = "arm"
    if len(lower) == 2:
        for o in lower:
            o.kind = "leg"
    if central:
        top = max(central, key=lambda o: o.centre[2])
        top.kind = "neck" if len(upper) == 2 else "waist"
        low = [o for o in central if o is not top and o.centre[2] < zlo + 0.5 * (zhi - zlo)]
        if low and len(lower) != 2:
            min(low, key=lambda o: o.centre[2]).kind = "hem"
    return ops


def lateral_axis(openings) -> np.ndarray | None:
    """[3] horizontal unit vector from one arm (else leg) opening to the other, or None."""
    for kind in ("arm", "leg"):
        pair = [o for o in openings if o.kind == kind]
        if len(pair) == 2:
            d = pair[1].centre - pair[0].centre
            d[2] = 0.0
            if np.linalg.norm(d) > 1e-6:
                return d / np.linalg.norm(d)
    return None


def rotation_between(a, b) -> np.ndarray:
    """[3] axis-angle of the smallest rotation taking direction a to direction b
    (body.retarget.rotation_between, as axis-angle)."""
    from ..body.model import matrix_to_axis_angle
    from ..body.retarget import rotation_between as matrix_between

    return matrix_to_axis_angle(matrix_between(np.asarray(a, float), np.asarray(b, float)))


def limb_pose(body, openings, joints=None) -> tuple[np.ndarray, dict]:
    """(rotations [B, 3], per limb bone the aim) putting each arm and leg of ``body`` through its
    opening (module docstring); ``openings`` placed on the body in its rest pose (``joints`` [B, 3],
    default the rest joints). World-aligned rotations (body.model): only the limb root bones turn,
    the rest of each limb follows unbent relative to it."""
    names = list(body.bone_names)
    J = body.rest_joints if joints is None else np.asarray(joints)
    rots = np.zeros((len(names), 3))
    aims = {}
    mid = J[names.index("root")] if "root" in names else J.mean(0)
    for kind, root, end in (("arm", ARM_ROOT, ARM_END), ("leg", LEG_ROOT, LEG_END)):
        for o in (o for o in openings if o.kind == kind):
            side = "L" if o.centre[0] > mid[0] else "R"
            try:
                r, e = names.index(f"{root}.{side}"), names.index(f"{end}.{side}")
            except ValueError:
                continue
            to = o.centre - J[r]
            d = o.normal if np.linalg.norm(to) < 1.5 * o.radius else to
            rots[r] = rotation_between(J[e] - J[r], d)
            aims[names[r]] = {"opening": kind, "towards": "normal" if d is o.normal else "centre",
                              "angle_deg": round(float(np.degrees(np.linalg.norm(rots[r]))), 1)}
            w = names.index(f"{WRIST}.{side}") if kind == "arm" and f"{WRIST}.{side}" in names else None
            if w is not None:  # the forearm straight on: a bent elbow pokes out of a sleeve or armhole
                rots[e] = rotation_between(J[w] - J[e], J[e] - J[r])
            f = names.index(f"{FOOT}.{side}") if kind == "leg" and f"{FOOT}.{side}" in names else None
            if f is not None and np.linalg.norm(to) > 0.8 * np.linalg.norm(J[f] - J[r]):
                # a trouser leg down to the ankle: the foot points down the leg (through the cuff)
                kids = np.flatnonzero(np.asarray(body.parents) == f)
                if len(kids):
                    rots[f] = rotation_between(J[kids].mean(0) - J[f], J[e] - J[r])
                    aims[names[f]] = {"opening": kind, "towards": "along the leg",
                                      "angle_deg": round(float(np.degrees(np.linalg.norm(rots[f]))), 1)}
    return rots, aims
