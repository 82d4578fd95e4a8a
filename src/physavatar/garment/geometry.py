"""Closest points on triangle meshes, mesh quality and mesh adjacency (numpy + scipy only)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


def closest_point_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates [n, 3] of the closest point on triangles (a, b, c) to points p.

    Ericson, Real-Time Collision Detection, 5.1.5, vectorized over n point-triangle pairs.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    n = len(p)
    w = np.zeros((n, 3))
    done = np.zeros(n, bool)

    def put(mask, vals):
        m = mask & ~done
        w[m] = vals[m]
        done[:] |= m

    one = np.ones(n)
    zero = np.zeros(n)

    def c3(x, y, z):
        return np.stack([x, y, z], axis=1)

    put((d1 <= 0) & (d2 <= 0), c3(one, zero, zero))
    put((d3 >= 0) & (d4 <= d3), c3(zero, one, zero))
    with np.errstate(divide="ignore", invalid="ignore"):
        v = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), c3(1 - v, v, zero))
        put((d6 >= 0) & (d5 <= d6), c3(zero, zero, one))
        t = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), c3(1 - t, zero, t))
        u = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), c3(zero, 1 - u, u))
        den = 1.0 / (va + vb + vc)
        vv, ww = vb * den, vc * den
        put(np.ones(n, bool), c3(1 - vv - ww, vv, ww))
    return w


def vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """[V, 3] area-weighted unit vertex normals."""
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n = np.zeros_like(V)
    for k in range(3):
        np.add.at(n, F[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


class MeshQuery:
    """Closest points on a fixed triangle mesh: exact point-triangle tests on candidate triangles
    found through a KD-tree of surface samples (every point of every triangle lies within
    ``spacing`` of one of its samples, which makes the candidate search provably complete)."""

    def __init__(self, V: np.ndarray, F: np.ndarray, spacing: float = 0.01):
        self.V, self.F = np.asarray(V, float), np.asarray(F, np.int64)
        tri = self.V[self.F]
        L = np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2).max(1)
        levels = np.maximum(1, np.ceil(L / spacing).astype(int))
        pts, ids = [tri.mean(1)], [np.arange(len(self.F))]
        for n in np.unique(levels[levels > 1]):
            sel = np.nonzero(levels == n)[0]
            i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
            keep = i + j <= n
            w = np.stack([(n - i - j)[keep], i[keep], j[keep]], 1) / n  # [s, 3]
            pts.append(np.einsum("sk,mkd->msd", w, tri[sel]).reshape(-1, 3))
            ids.append(np.repeat(sel, len(w)))
        self._samples = cKDTree(np.concatenate(pts))
        self._sample_face = np.concatenate(ids)
        # max distance from a point of a triangle to its nearest sample
        centroid_radius = np.linalg.norm(tri - tri.mean(1, keepdims=True), axis=2).max(1)
        self._rad = float(np.max(np.where(levels > 1, L / levels, centroid_radius)))
        self.normals = vertex_normals(self.V, self.F)

    def closest(self, P: np.ndarray, k: int = 24, max_dist: float = np.inf):
        """Closest points of P [n, 3]: (distance [n], face [n], barycentric [n, 3], point [n, 3]).

        Points farther than ``max_dist`` from the mesh get a distance that is only an upper bound
        (still > max_dist): use it when only near points matter.
        """
        P = np.atleast_2d(np.asarray(P, float))
        n_s = len(self._sample_face)
        k = min(k, n_s)
        d0, cs = self._samples.query(P, k=k)
        cs, d0 = cs.reshape(len(P), k), d0.reshape(len(P), k)
        cand = self._sample_face[cs]
        t = self.F[cand.ravel()]
        Pr = np.repeat(P, k, axis=0)
        w = closest_point_triangle(Pr, self.V[t[:, 0]], self.V[t[:, 1]], self.V[t[:, 2]])
        q = np.einsum("nk,nkd->nd", w, self.V[t])
        d = np.linalg.norm(Pr - q, axis=1).reshape(len(P), k)
        j = np.argmin(d, axis=1)
        r = np.arange(len(P))
        best_d, best_f = d[r, j], cand[r, j]
        best_w = w.reshape(len(P), k, 3)[r, j]
        # complete only if every sample within (best distance + sample radius) was looked at
        need = d0[:, -1] < np.minimum(best_d, max_dist) + self._rad
        if need.any() and k < n_s:
            idx = np.nonzero(need)[0]
            d2, f2, w2, _ = self.closest(P[idx], k=min(4 * k, n_s), max_dist=max_dist)
            better = d2 < best_d[idx]
            idx = idx[better]
            best_d[idx], best_f[idx], best_w[idx] = d2[better], f2[better], w2[better]
        q = np.einsum("nk,nkd->nd", best_w, self.V[self.F[best_f]])
        return best_d, best_f, best_w, q

    def signed_distance(self, P: np.ndarray, max_dist: float = np.inf):
        """Distance to the surface, negative inside (sign from the interpolated vertex normal)."""
        d, f, w, q = self.closest(P, max_dist=max_dist)
        n = np.einsum("nk,nkd->nd", w, self.normals[self.F[f]])
        s = np.sign(((P - q) * n).sum(1))
        s[s == 0] = 1.0
        return s * d, q, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def mesh_quality(V: np.ndarray, F: np.ndarray) -> dict:
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)

    def ang(p, q, r):
        u, v = q - p, r - p
        cosv = (u * v).sum(1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
        return np.degrees(np.arccos(np.clip(cosv, -1, 1)))

    angles = np.c_[ang(a, b, c), ang(b, c, a), ang(c, a, b)]
    edges = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
    el = np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1)
    return {"min_angle_deg": float(angles.min()), "max_angle_deg": float(angles.max()),
            "area_ratio": float(area.max() / area.min()), "mean_edge": float(el.mean()),
            "n_vertices": int(len(V)), "n_faces": int(len(F))}


def adjacency(F: np.ndarray, n: int) -> sp.csr_matrix:
    """[n, n] symmetric 0/1 vertex adjacency of a triangle mesh."""
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    A.data[:] = 1.0
    return A


def submesh(faces: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The part of a mesh on the vertices where ``mask`` [V] is true: (vertex ids [n] into the
    whole mesh, faces [f, 3] re-indexed on those ids); faces with all three corners selected."""
    mask = np.asarray(mask, bool)
    ids = np.flatnonzero(mask)
    remap = -np.ones(len(mask), np.int64)
    remap[ids] = np.arange(len(ids))
    return ids, remap[faces[mask[faces].all(1)]]


def mesh_edges(F: np.ndarray) -> np.ndarray:
    return np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)


def _edge_triangle_hits(EV, E, TV, T) -> int:
    """Number of (edge of mesh 1, triangle of mesh 2) pairs that intersect (ipctk's exact test on
    candidates whose bounding spheres overlap)."""
    import ipctk

    a, b = EV[E[:, 0]], EV[E[:, 1]]
    mid, r_e = 0.5 * (a + b), 0.5 * np.linalg.norm(b - a, axis=1)
    tri = TV[T]
    cen = tri.mean(1)
    r_t = np.linalg.norm(tri - cen[:, None], axis=2).max(1)
    tree = cKDTree(cen)
    lists = tree.query_ball_point(mid, r_e + r_t.max())
    hits = 0
    for i, cand in enumerate(lists):
        if not cand:
            continue
        cand = np.asarray(cand)
        cand = cand[np.linalg.norm(cen[cand] - mid[i], axis=1) <= r_e[i] + r_t[cand]]
        for t in cand:
            if ipctk.is_edge_intersecting_triangle(a[i], b[i], tri[t, 0], tri[t, 1], tri[t, 2]):
                hits += 1
    return hits


def count_intersections(V1, F1, V2, F2) -> int:
    """Intersecting edge-triangle pairs between two meshes, both ways (0: the surfaces are apart).

    ``ipctk.has_intersections`` on the union cannot be used here: the Anny body intersects itself
    in its rest pose (fingers, armpits), so only pairs across the two meshes are tested.
    """
    V1, V2 = np.asarray(V1, float), np.asarray(V2, float)
    return (_edge_triangle_hits(V1, mesh_edges(F1), V2, np.asarray(F2))
            + _edge_triangle_hits(V2, mesh_edges(F2), V1, np.asarray(F1)))
