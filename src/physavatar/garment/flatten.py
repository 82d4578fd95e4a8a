"""Flattening a panel's 3D surface into its sewing pattern: least-squares conformal maps.

A panel is first drawn in the frontal (x, z) plane and lifted to 3D as a height field
(``surface.PanelSurface``). That lift stretches the frontal plane wherever the cloth turns away
from the viewer (side seams, under the sleeves, over the shoulders), and a mesh that is uniform in
the frontal plane would have thin triangles there. So the lifted panel is sampled densely and
flattened with LSCM (Lévy et al. 2002): the flattening preserves angles, so triangles that are
well shaped in the pattern stay well shaped in 3D, and the remaining change of scale is handled
by Triangle's per-triangle area bound (``pattern.mesh_panel``). Pattern points are lifted back
by barycentric interpolation on the dense mesh.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import triangle as tr
from scipy.spatial import cKDTree


def cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z component of the cross product of 2D vectors [..., 2]."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def lscm(P: np.ndarray, T: np.ndarray, pin: tuple[int, int]) -> np.ndarray:
    """Least-squares conformal map of a disk-like mesh.

    Args:
        P: [n, 3] vertices; T: [m, 3] triangles; pin: two vertices fixed at (0, 0) and (d, 0)
            with d their 3D distance.
    Returns:
        [n, 2] pattern coordinates, scaled so the pattern's area equals the surface's area.
    """
    n = len(P)
    a, b, c = P[T[:, 0]], P[T[:, 1]], P[T[:, 2]]
    e1 = b - a
    l1 = np.linalg.norm(e1, axis=1)
    ex = e1 / l1[:, None]
    nrm = np.cross(e1, c - a)
    area = 0.5 * np.linalg.norm(nrm, axis=1)
    ey = np.cross(nrm / (2 * area)[:, None], ex)
    # local 2D coordinates of the triangle's corners
    q = np.stack([np.zeros((len(T), 2)), np.c_[l1, np.zeros(len(T))],
                  np.c_[((c - a) * ex).sum(1), ((c - a) * ey).sum(1)]], axis=1)  # [m, 3, 2]
    # gradient of a linear function from its corner values: G [m, 2, 3]
    rot = np.stack([q[:, 2] - q[:, 1], q[:, 0] - q[:, 2], q[:, 1] - q[:, 0]], axis=2)  # [m, 2, 3]
    G = np.stack([rot[:, 1], -rot[:, 0]], axis=1) / (2 * area)[:, None, None]
    w = np.sqrt(area)[:, None]
    # Cauchy-Riemann residuals: du/dx - dv/dy and du/dy + dv/dx, unknowns [u (n), v (n)]
    rows = np.arange(len(T))
    R, C, V = [], [], []
    for k in range(3):
        R += [rows, rows, len(T) + rows, len(T) + rows]
        C += [T[:, k], n + T[:, k], T[:, k], n + T[:, k]]
        V += [w[:, 0] * G[:, 0, k], -w[:, 0] * G[:, 1, k], w[:, 0] * G[:, 1, k], w[:, 0] * G[:, 0, k]]
    M = sp.csr_matrix((np.concatenate(V), (np.concatenate(R), np.concatenate(C))), shape=(2 * len(T), 2 * n))
    i, j = pin
    d = float(np.linalg.norm(P[i] - P[j]))
    fixed = np.array([i, j, n + i, n + j])
    vals = np.array([0.0, d, 0.0, 0.0])
    free = np.setdiff1d(np.arange(2 * n), fixed)
    A = M[:, free]
    rhs = -M[:, fixed] @ vals
    x = spla.spsolve((A.T @ A).tocsc(), A.T @ rhs)
    sol = np.empty(2 * n)
    sol[free], sol[fixed] = x, vals
    uv = np.c_[sol[:n], sol[n:]]
    a2 = 0.5 * np.abs(cross2(uv[T[:, 1]] - uv[T[:, 0]], uv[T[:, 2]] - uv[T[:, 0]])).sum()
    return uv * np.sqrt(area.sum() / a2)


def _local_frames(P, T):
    """[m, 3, 2] each triangle's corners in an isometric 2D frame of its plane."""
    a, b, c = P[T[:, 0]], P[T[:, 1]], P[T[:, 2]]
    e1 = b - a
    l1 = np.linalg.norm(e1, axis=1)
    ex = e1 / l1[:, None]
    nrm = np.cross(e1, c - a)
    ey = np.cross(nrm / np.linalg.norm(nrm, axis=1)[:, None], ex)
    return np.stack([np.zeros((len(T), 2)), np.c_[l1, np.zeros(len(T))],
                     np.c_[((c - a) * ex).sum(1), ((c - a) * ey).sum(1)]], axis=1)


def arap(P: np.ndarray, T: np.ndarray, uv: np.ndarray, iters: int = 10) -> np.ndarray:
    """As-rigid-as-possible flattening (Liu et al. 2008), started from ``uv``.

    LSCM keeps angles but shrinks long thin parts (shoulder straps) exponentially; the local-global
    ARAP iterations restore their lengths, so the pattern is close to isometric everywhere.
    """
    n = len(P)
    q = _local_frames(P, T)
    # half-cotangent weight of each edge (i, j) = corners (k+1, k+2), opposite corner k
    cot = np.empty((len(T), 3))
    for k in range(3):
        u = q[:, (k + 1) % 3] - q[:, k]
        v = q[:, (k + 2) % 3] - q[:, k]
        cot[:, k] = 0.5 * (u * v).sum(1) / np.maximum(np.abs(cross2(u, v)), 1e-16)
    # obtuse angles give negative weights that can fold the map; clamped weights keep the global
    # step a proper (M-matrix) Laplacian
    cot = np.clip(cot, 1e-3, None)
    I, J = T[:, [1, 2, 0]], T[:, [2, 0, 1]]  # edge opposite corner k
    w = cot.ravel()
    L = sp.coo_matrix((np.r_[w, w, -w, -w], (np.r_[I.ravel(), J.ravel(), I.ravel(), J.ravel()],
                                            np.r_[I.ravel(), J.ravel(), J.ravel(), I.ravel()])), shape=(n, n)).tocsc()
    keep = np.arange(1, n)  # vertex 0 pinned (ARAP is defined up to a rigid motion)
    solve = spla.splu(L[keep][:, keep].tocsc()).solve
    col0 = L[keep][:, [0]].toarray()[:, 0]
    dq = q[:, [1, 2, 0]] - q[:, [2, 0, 1]]  # [m, 3, 2] q_i - q_j for the edge opposite corner k
    for _ in range(iters):
        # local step: best rotation of each triangle (2x2 Procrustes)
        du = uv[I] - uv[J]
        S = np.einsum("mk,mki,mkj->mij", cot, du, dq)
        U, _, Vt = np.linalg.svd(S)
        R = U @ Vt
        neg = np.linalg.det(R) < 0
        U[neg, :, 1] *= -1
        R = U @ Vt
        # global step: Poisson solve for the vertex positions
        rhs_e = cot[..., None] * np.einsum("mij,mkj->mki", R, dq)  # [m, 3, 2]
        re = rhs_e.reshape(-1, 2)
        b = np.stack([np.bincount(I.ravel(), re[:, d], n) - np.bincount(J.ravel(), re[:, d], n) for d in range(2)], 1)
        new = uv.copy()
        for d in range(2):
            new[keep, d] = solve(b[keep, d] - col0 * uv[0, d])
        sa = cross2(new[T[:, 1]] - new[T[:, 0]], new[T[:, 2]] - new[T[:, 0]])
        if min((sa <= 0).sum(), (sa >= 0).sum()) > 0:
            break  # an iterate that folds the pattern is never used: keep the last fold-free one
        uv = new
    return uv


class FlatPanel:
    """A panel's dense 3D sampling and its LSCM pattern; lifts pattern points to 3D.

    Args:
        outline: [k, 2] closed frontal-plane polyline (not repeating its first point).
        lift: frontal (x, z) [n, 2] -> 3D [n, 3].
        spacing: dense sampling distance (m).
    """

    def __init__(self, outline: np.ndarray, lift, spacing: float):
        k = len(outline)
        seg = np.c_[np.arange(k), (np.arange(k) + 1) % k]
        a = np.sqrt(3) / 4 * spacing ** 2
        out = tr.triangulate({"vertices": outline, "segments": seg}, f"pq30a{a:.12f}YQ")
        self.frontal = out["vertices"]
        self.tris = out["triangles"].astype(np.int64)
        self.points = lift(self.frontal)
        # pin the outline's two points farthest apart (stable orientation: the first one left)
        o = outline
        i = int(np.argmin(o[:, 0] + 1e-3 * o[:, 1]))
        j = int(np.argmax(np.linalg.norm(o - o[i], axis=1)))
        uv = arap(self.points, self.tris, lscm(self.points, self.tris, (i, j)))
        # orient like the frontal plane: rotate so the frontal x axis maps to +u, and keep CCW
        d_fr = self.frontal[j] - self.frontal[i]
        ang = np.arctan2(d_fr[1], d_fr[0])
        c, s = np.cos(ang), np.sin(ang)
        uv = uv @ np.array([[c, s], [-s, c]])
        t = self.tris
        sa = cross2(uv[t[:, 1]] - uv[t[:, 0]], uv[t[:, 2]] - uv[t[:, 0]])
        if np.median(sa) < 0:
            uv[:, 1] *= -1
        self.uv = uv
        self._cent = cKDTree(uv[self.tris].mean(1))
        # the lift is linear on each dense triangle: its Jacobian d(3D)/d(pattern) [m, 3, 2]
        E3 = np.stack([self.points[t[:, 1]] - self.points[t[:, 0]], self.points[t[:, 2]] - self.points[t[:, 0]]], -1)
        E2 = np.stack([uv[t[:, 1]] - uv[t[:, 0]], uv[t[:, 2]] - uv[t[:, 0]]], -1)
        self._jac = E3 @ np.linalg.inv(E2)
        self.n_outline = k

    def _locate(self, uv):
        # the containing triangle among the nearest few (or, just outside the outline, the one
        # the point is least outside of: barycentric extrapolation)
        uv = np.atleast_2d(uv)
        _, cand = self._cent.query(uv, k=min(10, len(self.tris)))
        t = self.tris[cand]  # [n, k, 3]
        A, B, C = self.uv[t[..., 0]], self.uv[t[..., 1]], self.uv[t[..., 2]]
        p = uv[:, None, :]
        d = (B[..., 0] - A[..., 0]) * (C[..., 1] - A[..., 1]) - (B[..., 1] - A[..., 1]) * (C[..., 0] - A[..., 0])
        d = np.where(np.abs(d) < 1e-20, 1e-20, d)
        l1 = ((p[..., 0] - A[..., 0]) * (C[..., 1] - A[..., 1]) - (p[..., 1] - A[..., 1]) * (C[..., 0] - A[..., 0])) / d
        l2 = ((B[..., 0] - A[..., 0]) * (p[..., 1] - A[..., 1]) - (B[..., 1] - A[..., 1]) * (p[..., 0] - A[..., 0])) / d
        lam = np.stack([1 - l1 - l2, l1, l2], axis=-1)
        best = np.argmax(lam.min(-1), axis=1)
        r = np.arange(len(uv))
        return t[r, best], lam[r, best], cand[r, best]

    def __call__(self, uv: np.ndarray) -> np.ndarray:
        """Pattern points [n, 2] -> 3D [n, 3]."""
        t, w, _ = self._locate(uv)
        return np.einsum("nk,nkd->nd", w, self.points[t])

    def to_frontal(self, uv: np.ndarray) -> np.ndarray:
        t, w, _ = self._locate(uv)
        return np.einsum("nk,nkd->nd", w, self.frontal[t])

    def jacobian(self, uv: np.ndarray) -> np.ndarray:
        """[n, 3, 2] d(3D)/d(pattern) of the piecewise-linear lift."""
        return self._jac[self._locate(uv)[2]]
