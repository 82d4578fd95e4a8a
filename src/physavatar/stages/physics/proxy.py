"""A coarse simulation proxy of a garment, for material estimation on big garments.

Fitting the material needs ~10 simulations of the fitted window with sensitivities, and one
plain simulation of a garment of a few thousand vertices takes minutes on a CPU. The material is a property of the fabric, not of the mesh, so ``fit-physics`` fits it on a
proxy of a few hundred vertices (docs/physics.md "Coarse proxy"):

1. the template garment is decimated by shortest-edge-first edge collapses (our own, a few
   dozen lines: works on any template, with or without a sewing pattern) to at most
   ``max_vertices`` vertices; the garment's boundary (Dirichlet) vertices and open border rank
   above interior vertices, so edges collapse into them: the attached regions (straps, a
   waistband) survive at their own positions and the outline stays on the fine outline
   (quadric decimation, e.g. pyfqmr, drops narrow straps altogether and leaves ~1° slivers);
2. the decimated mesh is improved for simulation: Delaunay edge flips (on nearly flat edges
   only, so the shape stays) and tangential smoothing of interior vertices projected back
   onto the template surface;
3. every proxy vertex is tied to the fine rest mesh by the barycentric coordinates of its
   closest point there, so any fine sequence [T, N, 3] maps to the proxy as [T, n, 3]
   (:meth:`GarmentProxy.map`): the tracked reference, the proxy's rest shape and its boundary
   targets all come from the fine data the same way;
4. the proxy's boundary (Dirichlet) vertices are the surviving fine ones (exact weights);
5. :func:`on_proxy` moves the fit's data (:class:`~.data.PhysicsData`) onto the proxy.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ...errors import PhysavatarError
from ...geometry import MeshQuery, vertex_normals
from .data import PhysicsData

PROXY_CLEARANCE = 0.003  # [m] the proxy's smallest distance to the body at rest (> d̂ = 1 mm)
GRADING_NEAR = 0.4  # relative edge length at the attachment
GRADING_REACH = 4.0  # distance [target edges] over which it grows to 1


@dataclasses.dataclass(frozen=True)
class GarmentProxy:
    """A coarse garment tied to a fine one.

    Attributes:
        vertices: [n, 3] proxy rest positions (on the fine rest surface).
        faces: [f, 3] proxy triangles (orientation of the fine mesh).
        boundary: [k] proxy Dirichlet vertices.
        corners: [n, 3] fine vertex ids of the fine triangle each proxy vertex lies on.
        weights: [n, 3] its barycentric coordinates there.
    """

    vertices: np.ndarray
    faces: np.ndarray
    boundary: np.ndarray
    corners: np.ndarray
    weights: np.ndarray

    def map(self, fine: np.ndarray) -> np.ndarray:
        """Fine per-vertex data [..., N, 3] -> proxy [..., n, 3] (barycentric interpolation)."""
        fine = np.asarray(fine, dtype=np.float64)
        return np.einsum("...nkd,nk->...nd", fine[..., self.corners, :], self.weights)

    @property
    def mean_edge(self) -> float:
        return _mean_edge(self.vertices, self.faces)


def make_proxy(vertices: np.ndarray, faces: np.ndarray, boundary: np.ndarray, max_vertices: int = 400,
               smoothing_rounds: int = 5) -> GarmentProxy:
    """Decimate the garment (rest ``vertices`` [N, 3], ``faces`` [F, 3], Dirichlet ids
    ``boundary`` [K]) to a simulation proxy of at most ``max_vertices`` vertices."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    boundary = np.unique(np.asarray(boundary, dtype=np.int64))
    if max_vertices < 20:
        raise PhysavatarError(None, f"a proxy needs at least 20 vertices, asked for {max_vertices}")
    v, f, kind = collapse_decimate(V, F, boundary, max_vertices)
    query = MeshQuery(V, F, spacing=0.5 * _mean_edge(V, F))
    movable = kind == 0
    for _ in range(smoothing_rounds):
        f = delaunay_flips(v, f)
        v = _smooth_tangential(v, f, query, movable)
    f = delaunay_flips(v, f)
    _, face, w, point = query.closest(v)
    return GarmentProxy(point, f, np.flatnonzero(kind == 2), F[face], w)


def collapse_decimate(V: np.ndarray, F: np.ndarray, boundary: np.ndarray, max_vertices: int):
    """Shortest-edge-first edge collapses down to ``max_vertices`` vertices.

    Vertices are ranked: Dirichlet (2) > open border (1) > interior (0). An edge collapses into
    its higher-ranked end, which stays where it is (so Dirichlet vertices survive at their own
    positions and the garment's outline stays on the fine outline); two interior ends meet at
    the midpoint; two border ends only along a border edge. The link condition keeps the mesh
    manifold and a normal test keeps triangles from folding over. Each pass collapses
    independent edges (no shared neighbours), shortest first, then rebuilds.

    Returns (vertices [n, 3], faces [f, 3], rank [n]).
    """
    V = np.array(V, dtype=np.float64)
    F = np.array(F, dtype=np.int64)
    n = len(V)
    rank = np.zeros(n, np.int64)
    u, w = _edges(F)
    key = np.minimum(u, w) * n + np.maximum(u, w)
    uniq, counts = np.unique(key, return_counts=True)
    border_keys = uniq[counts == 1]
    rank[border_keys // n] = 1
    rank[border_keys % n] = 1
    rank[boundary] = 2
    # Dirichlet vertices merge only while closer than the proxy's target edge (an equilateral
    # mesh of max_vertices vertices, ~2 triangles each), so an attachment keeps its extent
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum()
    h_target = math.sqrt(4.0 * area / (math.sqrt(3.0) * 2 * max_vertices))
    # graded: the garment hangs from its attachment, where the load and the strain concentrate
    # (straps); edges there collapse last, down to GRADING_NEAR × the size far away
    from scipy.spatial import cKDTree

    # (a garment held by contact alone, without Dirichlet vertices, is decimated uniformly)
    dist = cKDTree(V[boundary]).query(V)[0] if len(boundary) else np.full(n, np.inf)
    size = GRADING_NEAR + (1.0 - GRADING_NEAR) * np.minimum(1.0, dist / (GRADING_REACH * h_target))
    alive = n
    for _ in range(200):
        if alive <= max_vertices:
            break
        u, w = _edges(F)
        key = np.minimum(u, w) * n + np.maximum(u, w)
        uniq, counts = np.unique(key, return_counts=True)
        on_border = set(uniq[counts == 1].tolist())
        nbrs = [set() for _ in range(n)]
        for a, b in zip(u.tolist(), w.tolist()):
            nbrs[a].add(b)
            nbrs[b].add(a)
        faces_of = [[] for _ in range(n)]
        for fi, tri in enumerate(F.tolist()):
            for x in tri:
                faces_of[x].append(fi)
        ea, eb = uniq // n, uniq % n
        length = np.linalg.norm(V[ea] - V[eb], axis=1)
        order = np.argsort(length / (size[ea] + size[eb]))
        goal = max(1, min(alive - max_vertices, alive // 6))
        touched = np.zeros(n, bool)
        remap = np.arange(n)
        done = 0
        for e in order.tolist():
            if done >= goal:
                break
            a, b = int(ea[e]), int(eb[e])
            if touched[a] or touched[b]:
                continue
            if rank[a] < rank[b]:
                a, b = b, a  # a: the end that stays
            border_edge = int(uniq[e]) in on_border
            if rank[a] == rank[b] == 1 and not border_edge:
                continue  # would pinch the outline
            if rank[b] == 1 and rank[a] == 2 and not border_edge:
                continue
            if rank[a] == rank[b] == 2 and length[e] > GRADING_NEAR * h_target:
                continue
            common = nbrs[a] & nbrs[b]
            if len(common) != (1 if border_edge else 2):
                continue  # link condition
            if border_edge:
                c = next(iter(common))
                if min(a, c) * n + max(a, c) in on_border and min(b, c) * n + max(b, c) in on_border:
                    continue  # a three-edge hole would close
            p = 0.5 * (V[a] + V[b]) if rank[a] == rank[b] == 0 else V[a]
            if not _collapse_keeps_orientation(V, F, faces_of[b], faces_of[a], a, b, p):
                continue
            V[a] = p
            remap[b] = a
            touched[a] = touched[b] = True
            touched[list(nbrs[a] | nbrs[b])] = True
            done += 1
        if not done:
            break
        F = remap[F]
        F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 2] != F[:, 0])]
        alive -= done
    used = np.unique(F)
    new = -np.ones(n, np.int64)
    new[used] = np.arange(len(used))
    return V[used], new[F], rank[used]


def _collapse_keeps_orientation(V, F, faces_b, faces_a, a, b, p, min_cos=0.2):
    """After moving a and b to p, no face around them (other than those on edge ab) turns over
    or becomes degenerate."""
    for fi in set(faces_b) | set(faces_a):
        tri = F[fi]
        if a in tri and b in tri:
            continue
        P = V[tri].copy()
        P[(tri == a) | (tri == b)] = p
        n0 = np.cross(V[tri[1]] - V[tri[0]], V[tri[2]] - V[tri[0]])
        n1 = np.cross(P[1] - P[0], P[2] - P[0])
        l0, l1 = np.linalg.norm(n0), np.linalg.norm(n1)
        if l1 < 1e-3 * l0 or np.dot(n0, n1) < min_cos * l0 * l1:
            return False
    return True


def _mean_edge(V, F):
    return float(np.linalg.norm(V[F] - V[F[:, [1, 2, 0]]], axis=2).mean())


def _edges(f):
    """Per face-edge (face, local k): edge k runs F[k] -> F[k+1], opposite vertex F[k+2]."""
    u = f.ravel()
    w = f[:, [1, 2, 0]].ravel()
    return u, w


def delaunay_flips(V: np.ndarray, F: np.ndarray, max_dihedral_deg: float = 30.0, passes: int = 30) -> np.ndarray:
    """Flip interior edges whose two opposite angles sum to more than π (the intrinsic Delaunay
    criterion: flipping raises the smallest angle), on edges whose faces are within
    ``max_dihedral_deg`` of coplanar so the surface keeps its shape. Returns new faces [F, 3]."""
    F = np.array(F, dtype=np.int64)
    n = len(V)
    cos_max = np.cos(np.radians(max_dihedral_deg))
    for _ in range(passes):
        u, w = _edges(F)
        opp = F[:, [2, 0, 1]].ravel()
        key = np.minimum(u, w) * n + np.maximum(u, w)
        order = np.argsort(key, kind="stable")
        ks = key[order]
        pair = np.flatnonzero(ks[1:] == ks[:-1])
        a, b = order[pair], order[pair + 1]  # half-edges of one interior edge
        fa, fb = a // 3, b // 3
        p, q = opp[a], opp[b]
        ua, wa = u[a], w[a]

        def angle(at, x, y):
            e1, e2 = V[x] - V[at], V[y] - V[at]
            c = np.einsum("ij,ij->i", e1, e2) / np.maximum(np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), 1e-300)
            return np.arccos(np.clip(c, -1, 1))

        s = angle(p, ua, wa) + angle(q, ua, wa)
        na = np.cross(V[wa] - V[ua], V[p] - V[ua])
        nb = np.cross(V[ua] - V[wa], V[q] - V[wa])
        cosd = np.einsum("ij,ij->i", na, nb) / np.maximum(np.linalg.norm(na, axis=1) * np.linalg.norm(nb, axis=1), 1e-300)
        existing = set(ks.tolist())
        cand = np.flatnonzero((s > np.pi + 1e-6) & (cosd > cos_max) & (p != q))
        cand = cand[np.argsort(-s[cand])]
        used = np.zeros(len(F), bool)
        flipped = 0
        for c in cand:
            if used[fa[c]] or used[fb[c]]:
                continue
            pk = min(p[c], q[c]) * n + max(p[c], q[c])
            if pk in existing:
                continue
            # quad u, q, w, p (counter-clockwise): diagonal p–q
            F[fa[c]] = (ua[c], q[c], p[c])
            F[fb[c]] = (q[c], wa[c], p[c])
            used[fa[c]] = used[fb[c]] = True
            existing.add(pk)
            flipped += 1
        if not flipped:
            break
    return F


def _smooth_tangential(v, f, query: MeshQuery, movable, step: float = 0.5):
    """Move interior vertices towards their neighbours' mean within the tangent plane, then back
    onto the fine surface; border and Dirichlet vertices stay (the outline, the attachment)."""
    import scipy.sparse as sp

    n = len(v)
    u, w = _edges(f)
    A = sp.coo_matrix((np.ones(len(u)), (u, w)), shape=(n, n)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)
    key = np.minimum(u, w) * n + np.maximum(u, w)
    uniq, counts = np.unique(key, return_counts=True)
    border_keys = uniq[counts == 1]
    border = ~np.asarray(movable, bool)
    border[border_keys // n] = True
    border[border_keys % n] = True
    mean = (A @ v) / np.maximum(np.asarray(A.sum(1)).ravel(), 1)[:, None]
    nrm = vertex_normals(v, f)
    d = mean - v
    d -= np.einsum("ij,ij->i", d, nrm)[:, None] * nrm
    out = v.copy()
    out[~border] += step * d[~border]
    _, _, _, point = query.closest(out[~border])
    out[~border] = point
    return out


def on_proxy(data: PhysicsData, proxy) -> PhysicsData:
    """``data`` moved onto a :class:`GarmentProxy` of its garment.

    Every fine per-vertex sequence maps by the proxy's barycentric coordinates at rest: the
    reference (tracked positions), the rest shape, the initial state, and the proxy's boundary
    targets — the map of the fine positions with the fine boundary vertices at their targets
    (the tracked boundary, or a prescribed attachment). The body collider is unchanged. Rest
    shape and initial state are then pushed off the body frame 0 to ``PROXY_CLEARANCE`` where
    the proxy's chords dip into it (a few mm; the reference is not moved).
    """
    ref = proxy.map(data.reference)
    b = np.asarray(proxy.boundary, dtype=np.int64)
    driven = data.reference.copy()
    driven[:, data.boundary] = data.boundary_targets
    targets = proxy.map(driven)[:, b]
    rest = proxy.map(data.rest)
    initial = ref[0] if data.initial is None else proxy.map(data.initial)
    offset = 0.0
    if data.collider is not None and data.collider_faces is not None:
        # the proxy's flat triangles cut chords through the fine surface; over a convex body
        # part they can dip into it at rest (IPC needs an intersection-free start, and a
        # trapped proxy cannot sag like the garment): push them out to PROXY_CLEARANCE, and
        # free the body edges through a proxy triangle whose corners are clear, which a
        # vertex-wise push does not see (garment.push_clear; session 30: the prepared demo's
        # proxy crossed the collider in 6 pairs and equilibrium_rest refused its start). The
        # attachment stays where the fine one is; crossings left are refused downstream.
        from ...garment.garment import push_clear

        moved, _ = push_clear(initial, proxy.faces, data.collider[0], data.collider_faces, PROXY_CLEARANCE,
                              fixed=b)
        offset = moved - initial
    return PhysicsData(
        reference=ref, faces=proxy.faces, boundary=b, collider=data.collider, collider_faces=data.collider_faces,
        fps=data.fps, rest=rest + offset, boundary_targets=targets, targets_tracked=data.targets_tracked,
        initial=initial + offset,
    )
