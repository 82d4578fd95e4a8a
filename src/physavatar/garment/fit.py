"""Putting a garment made for another body onto the Anny body (the paper's redressing).

Two steps. :func:`align_garment` places the garment's world shape rigidly (a turn about the
vertical and a translation) and chooses how far to raise the arms: it minimises a robust
one-sided distance of the garment to the body, in which a vertex inside the body costs 1 plus
its depth in centimetres and one outside costs its distance up to 5 cm (saturating), so the
garment goes where most of it is close to the body without crossing it, which is where the
source garment was close to its own body. The search: the four quarter turns × the arm raises,
each with a scan of the height (2 cm steps) and a Nelder–Mead refinement of the translation
(scipy). :func:`growing_bodies` then gives the body sequence of the settling simulation
(garment_sim.fit_on_body): from the body shrunk enough to clear the garment's deepest
crossing (arms raised as aligned) to the full body in its rest pose: each body vertex scaled
towards its main bone's axis (a trunk vertex towards the spine line), by the largest factor
that clears the garment. A garment whose 2 % deepest
vertices still cross the body by more than 3 mm where it fits best is graded up (uniformly, about its top, rest shape
too) in 4 % steps up to 20 %: it was made for a smaller body.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import PhysavatarError
from ..geometry import MeshQuery, vertex_normals

ARM_RAISES = (0.0, 30.0)  # degrees: candidate raises of the upper arms while aligning
ARM_RAISES_GROW = (0.0, 20.0, 35.0, 50.0)  # and while growing: the one a sleeve holds best
ANCHOR_SCALE = 0.05  # m: an opening this far off its body axis (neck, spine) costs as much as the whole closeness


@dataclass
class Alignment:
    """The garment's rigid placement on the body.

    Attributes:
        vertices: [N, 3] the garment's world shape placed on the body.
        yaw: degrees about +z; translation: [3] m; arm_raise: degrees the arms are raised by.
        body_vertices: [Nb, 3] the body the garment was placed on (arms raised).
        depth: deepest garment vertex inside that body [m] (0 = none inside).
        cost: the alignment cost (module docstring); near_fraction: share of vertices within 2 cm.
        grade: the uniform scale the garment was graded by (1 = its own size; rest shape too).
    """

    vertices: np.ndarray
    yaw: float
    translation: np.ndarray
    arm_raise: float
    body_vertices: np.ndarray
    depth: float
    cost: float
    near_fraction: float
    grade: float = 1.0
    faces: np.ndarray | None = None
    pose: np.ndarray | None = None  # [B, 3] limb pose from the garment's openings (None: arm_raise)
    aims: dict | None = None  # per posed limb bone: the opening it aims through, how, by how much

    def rotations(self, body) -> np.ndarray:
        """[B, 3] the pose the garment was placed on: the openings' limb pose, else the arm raise."""
        return self.pose if self.pose is not None else arms_raised(body, self.arm_raise)[0]

    def report(self) -> dict:
        out = {"yaw_deg": round(float(self.yaw), 2), "translation_m": [round(float(v), 4) for v in self.translation],
               "arm_raise_deg": self.arm_raise, "depth_m": round(self.depth, 4), "cost": round(self.cost, 4),
               "near_fraction": round(self.near_fraction, 3), "grade": self.grade}
        if self.aims is not None:
            out["limb_pose"] = self.aims
        return out


def _rot_z(deg):
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def arms_raised(body, degrees: float) -> np.ndarray:
    """Pose rotations [1, B, 3] raising both upper arms by ``degrees`` (about the front axis,
    each towards its own side's up) from the rest pose."""
    rots = np.zeros((1, len(body.bone_names), 3))
    if degrees == 0.0:
        return rots
    w = np.ones(1)
    for name in body.bone_names:
        if name.startswith("upperarm01"):
            i = body.bone_names.index(name)
            side = np.sign(body.rest_joints[i, 0]) or 1.0
            rots[:, i, 1] = -side * np.deg2rad(degrees) * w  # about y: +x arm up for a negative angle
    return rots


class _Surface:
    """A surface sampled densely (every ~5 mm) with normals: nearest-sample distances, signed by
    the sample's normal, in a KD-tree (scipy): the alignment search's thousands of evaluations."""

    def __init__(self, V, F, spacing=0.005):
        from scipy.spatial import cKDTree

        V, F = np.asarray(V, float), np.asarray(F, np.int64)
        N = vertex_normals(V, F)
        tri = V[F]
        n = int(np.clip(np.ceil(np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1).max() / spacing), 1, 12))
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        w = np.stack([(n - i - j)[keep], i[keep], j[keep]], 1) / n
        self.P = np.einsum("sk,fkd->fsd", w, tri).reshape(-1, 3)
        nn = np.einsum("sk,fkd->fsd", w, N[F]).reshape(-1, 3)
        self.N = nn / np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-12)
        self.tree = cKDTree(self.P)

    def signed(self, X):
        d, i = self.tree.query(X, distance_upper_bound=0.2)
        i = np.minimum(i, len(self.P) - 1)
        s = np.sign(np.einsum("nd,nd->n", X - self.P[i], self.N[i]))
        return np.where(np.isfinite(d), np.where(s < 0, -1.0, 1.0) * d, 0.2)


def _cost(body: _Surface, P: np.ndarray, Bz: np.ndarray) -> float:
    """Two-sided closeness of garment samples P to the body and of the body samples Bz (those in
    the garment's height range) to the garment: each term saturates at 5 cm; a garment sample
    inside the body costs more the deeper it is (the growing body corrects a few centimetres)."""
    from scipy.spatial import cKDTree

    sd = body.signed(P)
    g = np.where(sd < 0, np.minimum(1.0, 0.2 + (-sd) / 0.04), np.minimum(sd, 0.05) / 0.05).mean()
    top = P[:, 2] > P[:, 2].max() - 0.1 * np.ptp(P[:, 2])  # a garment hangs from its top: it rests there
    g += np.minimum(np.abs(sd[top]), 0.05).mean() / 0.05
    lo, hi = P[:, 2].min(), P[:, 2].max()
    sel = Bz[(Bz[:, 2] > lo) & (Bz[:, 2] < hi)]
    if not len(sel):
        return 2.0
    d = cKDTree(P).query(sel, distance_upper_bound=0.05)[0]
    return float(g + np.minimum(d, 0.05).mean() / 0.05)


def align_garment(vertices, body, *, faces=None, arm_raises=ARM_RAISES, samples: int = 800, seed: int = 0,
                  grades=(1.04, 1.08, 1.12, 1.16, 1.2), max_depth: float = 0.003) -> Alignment:
    """Place a garment's world shape [N, 3] (z up, metres) on ``body`` (a BodyModel) in its rest
    pose, arms raised as the search finds best (module docstring)."""
    from scipy.optimize import minimize

    V = np.asarray(vertices, dtype=np.float64)
    rng = np.random.default_rng(seed)
    S = V[rng.choice(len(V), size=min(samples, len(V)), replace=False)]
    c0 = 0.5 * (V.min(0) + V.max(0))
    trials = []  # (cost, yaw, t, raise, body index)
    bodies = []
    for raise_deg in arm_raises:
        rots = arms_raised(body, raise_deg)
        B = body.pose(rots, np.zeros((1, 3))).vertices[0] if raise_deg else body.rest_vertices
        surf = _Surface(B, body.faces)
        Bz = surf.P[rng.choice(len(surf.P), size=min(4000, len(surf.P)), replace=False)]
        bodies.append((B, surf, Bz))
        zmin, zmax = B[:, 2].min(), B[:, 2].max()
        for yaw in (0.0, 90.0, 180.0, 270.0):
            P = (S - c0) @ _rot_z(yaw).T
            h = P[:, 2].max()
            for top in np.arange(zmin + 0.2, zmax + 0.01, 0.02):  # where the garment's top sits
                band = (B[:, 2] > top - 0.5 * (P[:, 2].max() - P[:, 2].min())) & (B[:, 2] < top)
                xy = B[band, :2].mean(0) if band.any() else np.zeros(2)
                t = np.array([xy[0], xy[1], top - h])
                trials.append((_cost(surf, P + t, Bz), yaw, t, raise_deg, len(bodies) - 1))
    trials.sort(key=lambda r: r[0])
    best = None
    for cost0, yaw, t0, raise_deg, bi in trials[:4]:
        P = (S - c0) @ _rot_z(yaw).T
        _, surf, Bz = bodies[bi]
        res = minimize(lambda t, surf=surf, P=P, Bz=Bz: _cost(surf, P + t, Bz), t0, method="Nelder-Mead",
                       options={"initial_simplex": t0 + np.vstack([np.zeros(3), 0.02 * np.eye(3)]),
                                "xatol": 1e-3, "fatol": 1e-4, "maxfev": 120})
        if best is None or res.fun < best[0]:
            best = (float(res.fun), yaw, res.x.copy(), raise_deg, bodies[bi][0])
    cost, yaw, t, raise_deg, B = best
    placed = (V - c0) @ _rot_z(yaw).T + t
    placed, sd, grade = _graded(placed, MeshQuery(B, body.faces), grades, max_depth)
    return Alignment(placed, yaw, t - c0 @ _rot_z(yaw).T, raise_deg, B, float(max(0.0, -sd.min())), cost,
                     float(np.mean(np.abs(sd) < 0.02)), grade, faces)


def _graded(placed, Q, grades, max_depth):
    """(vertices, signed distances, grade): the placed garment graded up (uniformly about its top,
    where it hangs from) by the first of ``grades`` at which its 2 % deepest vertices cross the
    body by at most ``max_depth`` (a few vertices deeper, a sleeve across an arm, are the growing
    body's), else by the last."""
    grade = 1.0
    sd = Q.signed_distance(placed, max_dist=0.1)[0]
    for g in grades:
        if -np.percentile(sd, 2) <= max_depth:
            break
        top = placed[:, 2].max()
        centre = np.r_[placed[:, :2].mean(0), top]
        placed = centre + (placed - centre) * (g / grade)
        sd, grade = Q.signed_distance(placed, max_dist=0.1)[0], g
    return placed, sd, grade


def align_with_openings(vertices, body, faces, seams=None, *, samples: int = 800, seed: int = 0,
                        grades=(1.04, 1.08, 1.12, 1.16, 1.2), max_depth: float = 0.003) -> Alignment | None:
    """Place a garment with sleeves or trouser legs on ``body`` with its limbs posed through the
    garment's openings (garment.openings), or None when it has no pair of arm or leg openings.

    The garment's lateral axis (from one arm or leg opening to the other) is turned onto the
    body's x axis (two turns: front and back); the neck opening's centre is put at the base of
    the neck (neck01 joint), or the middle of the leg openings under the root joint, and the height
    scanned (2 cm steps, ±14 cm) with the limbs posed through the openings at each height; the best
    translation refined by Nelder–Mead (scipy) on the closeness cost (_cost) on the posed body plus
    the distance of the neck opening's centre from the neck's axis (or of the waist's from the
    spine's, horizontally and along it) over ``ANCHOR_SCALE``: the neck passes through the neck
    opening, however loose the garment; the pose solved again there. Graded up as :func:`align_garment`."""
    from scipy.optimize import minimize

    from .openings import find_openings, lateral_axis, limb_pose

    V = np.asarray(vertices, dtype=np.float64)
    ops = find_openings(V, faces, seams)
    L = lateral_axis(ops)
    if L is None:
        return None
    names = list(body.bone_names)
    J0 = body.rest_joints
    rng = np.random.default_rng(seed)
    S = V[rng.choice(len(V), size=min(samples, len(V)), replace=False)]
    c0 = 0.5 * (V.min(0) + V.max(0))
    neck = [o for o in ops if o.kind == "neck"]
    legs = [o for o in ops if o.kind == "leg"]
    if not neck and len(legs) != 2:  # arm openings but no neck to place them by
        return None
    yaw0 = -np.degrees(np.arctan2(L[1], L[0]))

    def posed(R, t):  # the body posed through the openings of the garment placed at R (x - c0) + t
        rots, aims = limb_pose(body, [o.moved(R, t - c0, c0) for o in ops])
        B = body.pose(rots[None], np.zeros((1, 3))).vertices[0]
        surf = _Surface(B, body.faces)
        Bz = surf.P[np.random.default_rng(seed).choice(len(surf.P), size=min(4000, len(surf.P)), replace=False)]
        return rots, aims, B, surf, Bz

    best = None
    for yaw in (yaw0, yaw0 + 180.0):
        R = _rot_z(yaw)
        P = (S - c0) @ R.T
        if neck:  # the neck opening's centre at the base of the neck
            anchor, target = R @ (neck[0].centre - c0), J0[names.index("neck01")].copy()
        else:  # the middle of the leg openings under the root, the waist at the waist
            waist = [o for o in ops if o.kind == "waist"]
            anchor = R @ (0.5 * (legs[0].centre + legs[1].centre) - c0)
            target = J0[names.index("root")].copy()
            if waist:
                anchor[2] = (R @ (waist[0].centre - c0))[2]
                target[2] = J0[names.index("spine03"), 2] if "spine03" in names else target[2] + 0.1
        t_base = target - anchor
        if neck:  # the neck passes through the neck opening: its centre near the neck's axis
            seg = (J0[names.index("neck01")] - [0.0, 0.0, 0.06], J0[names.index("head")])
        else:  # the waist's centre above the middle of the leg openings, over the spine
            seg = (J0[names.index("root")] - [0.0, 0.0, 0.2], J0[names.index("root")] + [0.0, 0.0, 0.4])
        a, d = seg[0], seg[1] - seg[0]

        def cost(x, surf, P, Bz, anchor=anchor, a=a, d=d):
            q = anchor + x
            off = np.linalg.norm(q - _closest_on_segments(q[None], a[None], d[None])[0])
            return _cost(surf, P + x, Bz) + off / ANCHOR_SCALE

        trials = []
        for dz in np.arange(-0.14, 0.141, 0.02):
            t = t_base + np.array([0.0, 0.0, dz])
            rots, aims, B, surf, Bz = posed(R, t)
            trials.append((cost(t, surf, P, Bz), dz))
        trials.sort()
        t = t_base + np.array([0.0, 0.0, trials[0][1]])
        for _ in range(2):  # refine on the posed body, then pose again where it went
            rots, aims, B, surf, Bz = posed(R, t)
            res = minimize(cost, t, args=(surf, P, Bz), method="Nelder-Mead",
                           options={"initial_simplex": t + np.vstack([np.zeros(3), 0.02 * np.eye(3)]),
                                    "xatol": 1e-3, "fatol": 1e-4, "maxfev": 120})
            t = res.x.copy()
        rots, aims, B, surf, Bz = posed(R, t)
        c = cost(t, surf, P, Bz)
        if best is None or c < best[0]:
            best = (c, yaw, t, rots, aims, B)
    cost, yaw, t, rots, aims, B = best
    placed = (V - c0) @ _rot_z(yaw).T + t
    placed, sd, grade = _graded(placed, MeshQuery(B, body.faces), grades, max_depth)
    return Alignment(placed, float(yaw % 360.0), t - c0 @ _rot_z(yaw).T, 0.0, B, float(max(0.0, -sd.min())), float(cost),
                     float(np.mean(np.abs(sd) < 0.02)), grade, faces, rots, aims)


TRUNK = ("root", "pelvis", "spine", "clavicle", "shoulder01", "neck", "head")  # shrunk towards the spine line
CHAIN = ("root", "spine04", "spine03", "spine02", "spine01", "neck01", "neck02", "neck03", "head")


def _closest_on_segments(P, a, d):
    """Closest points of P [n, 3] on segments a [n, 3] + t d [n, 3], t ∈ [0, 1]."""
    t = np.clip(np.einsum("nd,nd->n", P - a, d) / np.maximum(np.einsum("nd,nd->n", d, d), 1e-12), 0.0, 1.0)
    return a + t[:, None] * d


def _axis_points(body, joints, V):
    """Per body vertex of V [Nb, 3] (posed with joints [B, 3]), the point it shrinks towards: the
    skinning-weighted mean of its bones' targets, the closest point on a limb bone's axis (head
    to the mean of its children's heads), on the spine line (root, spine, neck, head joints) for
    a trunk bone, whose clavicle and shoulder axes run just under the skin of the chest. Blended
    as skinning blends (not each vertex to its main bone), a vertex where trunk and limb meet
    goes between their axes, and the shrunk body does not fold there."""
    names = list(body.bone_names)
    W = np.asarray(body.skinning_weights)
    parents = np.asarray(body.parents)
    end = joints.copy()
    for j in range(len(joints)):
        kids = np.flatnonzero(parents == j)
        if len(kids):
            end[j] = joints[kids].mean(0)
    trunk = np.array([n.startswith(TRUNK) for n in names])
    q = np.zeros_like(V)
    wsum = np.zeros(len(V))
    wt = W[:, trunk].sum(1)
    sel = np.flatnonzero(wt > 1e-4)
    if len(sel):
        chain = np.array([joints[names.index(n)] for n in CHAIN if n in names])
        chain = np.vstack([chain, chain[-1] + [0.0, 0.0, 0.2]])  # through the head
        Vt = V[sel]
        best = np.full(len(Vt), np.inf)
        qt = np.zeros_like(Vt)
        for k in range(len(chain) - 1):
            c = _closest_on_segments(Vt, np.broadcast_to(chain[k], Vt.shape), np.broadcast_to(chain[k + 1] - chain[k], Vt.shape))
            dist = np.linalg.norm(Vt - c, axis=1)
            better = dist < best
            best[better], qt[better] = dist[better], c[better]
        q[sel] += wt[sel, None] * qt
        wsum[sel] += wt[sel]
    for b in np.flatnonzero(~trunk):
        sel = np.flatnonzero(W[:, b] > 1e-4)
        if len(sel):
            n = len(sel)
            c = _closest_on_segments(V[sel], np.broadcast_to(joints[b], (n, 3)), np.broadcast_to(end[b] - joints[b], (n, 3)))
            q[sel] += W[sel, b, None] * c
            wsum[sel] += W[sel, b]
    return q / np.maximum(wsum, 1e-12)[:, None]


def _shrunk(V, q, alpha):
    return q + alpha * (V - q)


def _posed(body, rots, s):
    """(vertices [K, Nb, 3], joints [K, B, 3]) posed by rotations rots [B, 3] × (1 − s) for s [K]
    (each limb's single root rotation scaled: the shortest way back to the rest pose)."""
    if np.any(rots):
        pb = body.pose(np.asarray(rots)[None] * (1 - s)[:, None, None], np.zeros((len(s), 3)))
        return pb.vertices, pb.joints
    return np.repeat(body.rest_vertices[None], len(s), axis=0), np.repeat(body.rest_joints[None], len(s), axis=0)


def _start_girth(body, V, F, rots, dhat, min_alpha):
    """(α, vertices left): the largest α in 1, 0.9, … ≥ min_alpha at which the body (posed by
    rots) shrunk towards its bones leaves every garment vertex outside by 2 d̂ and no
    triangle crossing it (0 left), else the α that leaves the fewest vertices closer than 2 d̂."""
    from ..geometry import count_intersections

    P, J = _posed(body, rots, np.zeros(1))
    axes = _axis_points(body, J[0], P[0])
    best = None
    for alpha in np.arange(1.0, min_alpha - 1e-9, -0.1):
        B0 = _shrunk(P[0], axes, alpha)
        sd = MeshQuery(B0, body.faces).signed_distance(V, max_dist=0.05)[0]
        if sd.min() > 2 * dhat and (F is None or count_intersections(V, F, B0, body.faces) == 0):
            return float(alpha), 0
        left = int(np.sum(sd <= 2 * dhat))
        if best is None or left < best[1]:  # (shrunk further, a body can fold where trunk meets limb)
            best = (float(alpha), left)
    return best


def growing_bodies(body, alignment: Alignment, frames: int, hold: int, *, dhat: float = 1e-3,
                   min_alpha: float = 0.3, arm_raises=ARM_RAISES_GROW, max_left: float = 0.02,
                   pose_frames: int = 0) -> tuple[np.ndarray, float]:
    """(body vertices [frames + pose_frames + hold + 1, Nb, 3], start girth α₀): the body shrunk
    towards its bones (each vertex towards the axis of its main bone, by α₀: no part turns inside
    out, as an offset along the normals would turn a thin arm), posed as the garment was placed,
    growing (smoothstep α₀ → 1) to the full body, then held ``hold`` frames.

    A garment placed with its openings' limb pose (``alignment.pose``) grows in that pose over
    ``frames``, then the limbs turn back to the rest pose over ``pose_frames`` (smoothstep).
    Otherwise the arms are lowered while growing; the arm raise is the one of ``arm_raises`` (and
    the aligned one) that needs the least shrinking (a sleeve must hold its arm). α₀ is the largest
    of 1, 0.9, … that leaves every garment vertex outside the shrunk body by 2 d̂ and no garment
    triangle crossing it, or ``min_alpha`` when up to ``max_left`` of the vertices are still too
    close there (the start repair pushes those out); refused beyond."""
    best = None  # (α₀, rotations, vertices still too close at α₀ (left to the start repair), raise)
    if alignment.pose is not None:
        candidates = [(alignment.arm_raise, alignment.pose)]
    else:
        candidates = [(r, arms_raised(body, r)[0]) for r in dict.fromkeys((alignment.arm_raise,) + tuple(arm_raises))]
    for raise_deg, rots in candidates:
        a0, left = _start_girth(body, alignment.vertices, alignment.faces, rots, dhat, min_alpha)
        if best is None or (left, -a0) < (best[2], -best[0]):
            best = (a0, rots, left, raise_deg)
        if a0 == 1.0:
            break
    if best[2] > max_left * len(alignment.vertices):
        how = ("with its limbs posed through the garment's openings" if alignment.pose is not None else
               f"arms raised by any of {', '.join(f'{a:g}' for a in arm_raises)} degrees")
        raise PhysavatarError(None, f"the garment crosses the body where it fits best (by {alignment.depth * 100:.1f} cm) "
                                    f"and still does on the body shrunk to {min_alpha:.0%} of its girth, {how}: "
                                    "it was not made for a body like this")
    alpha0, rots, _, alignment.arm_raise = best
    s = np.linspace(0.0, 1.0, frames + 1)
    s = s * s * (3 - 2 * s)
    if alignment.pose is not None and pose_frames:
        u = np.linspace(0.0, 1.0, pose_frames + 1)[1:]
        u = u * u * (3 - 2 * u)
        grow = np.r_[s, np.ones(pose_frames)]  # growing, then turning the limbs back at full size
        unpose = np.r_[np.zeros(frames + 1), u]
    else:
        grow, unpose = s, s
    posed, joints = _posed(body, rots, unpose)
    out = np.empty_like(posed)
    for k in range(len(grow)):
        out[k] = _shrunk(posed[k], _axis_points(body, joints[k], posed[k]), alpha0 + (1 - alpha0) * grow[k])
    out = np.concatenate([out, np.repeat(out[-1:], hold, axis=0)])
    return out, alpha0
