"""Closest points on triangle meshes: the point-triangle test and a mesh query (numpy + scipy)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .mesh import vertex_normals


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
