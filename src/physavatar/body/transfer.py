"""Skinning weights for the captured body: transfer from the posed Anny body, then inpainting.

Paper A.2, after Abdrashitov et al. 2023 ("Robust skin weights transfer via weight inpainting"):

1. Closest-point transfer: each template vertex takes the barycentric blend of Anny's weights at
   its closest point on the posed Anny surface, *if* position and normal agree (distance below
   ``max_distance`` and normals within ``max_angle_deg``). Those vertices are "matched".
2. Inpainting: the weights of the unmatched vertices minimize the smoothness energy
   wᵀ Q w, with Q = −L + L M⁻¹ L (L the cotangent Laplacian, M the lumped mass; the sum of the
   Dirichlet energy and the squared-Laplacian energy of the paper), the matched weights held
   fixed. It is one sparse solve for all bones at once (a shared matrix, B right-hand sides).
3. Weights are clamped to be non-negative and renormalized to sum to one.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..geometry import MeshQuery, vertex_normals


def cotangent_laplacian(V: np.ndarray, F: np.ndarray) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """(L, M): L [V, V] negative semi-definite cotangent Laplacian, M [V, V] lumped (barycentric) mass."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    n = len(V)
    rows, cols, vals = [], [], []
    area = np.zeros(n)
    for k in range(3):
        i, j, o = F[:, k], F[:, (k + 1) % 3], F[:, (k + 2) % 3]
        u, w = V[i] - V[o], V[j] - V[o]
        cross = np.linalg.norm(np.cross(u, w), axis=1)
        cot = np.einsum("ij,ij->i", u, w) / np.maximum(cross, 1e-12)
        rows += [i, j]
        cols += [j, i]
        vals += [0.5 * cot, 0.5 * cot]
    a = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    for k in range(3):
        np.add.at(area, F[:, k], a / 3.0)
    W = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    L = W - sp.diags(np.asarray(W.sum(1)).ravel())
    M = sp.diags(np.maximum(area, 1e-12))
    return L.tocsr(), M.tocsr()


def closest_point_transfer(target_V, target_F, source_V, source_F, source_W, max_distance: float = 0.03,
                           max_angle_deg: float = 30.0):
    """Weights [N, B] at the closest source points and the matched mask [N].

    Args:
        target_V: [N, 3], target_F: [Ft, 3]: the mesh receiving weights.
        source_V: [Ns, 3], source_F: [Fs, 3], source_W: [Ns, B]: the posed Anny body and its weights.
    """
    _, f, bary, q = MeshQuery(source_V, source_F).closest(np.asarray(target_V, np.float64))
    tri = np.asarray(source_F)[f]
    W = np.einsum("nk,nkb->nb", bary, np.asarray(source_W)[tri])
    d = np.linalg.norm(np.asarray(target_V) - q, axis=1)
    ns = vertex_normals(np.asarray(source_V, np.float64), np.asarray(source_F), eps=1e-12)
    n_src = np.einsum("nk,nkd->nd", bary, ns[tri])
    n_src /= np.maximum(np.linalg.norm(n_src, axis=1, keepdims=True), 1e-12)
    n_tgt = vertex_normals(np.asarray(target_V, np.float64), np.asarray(target_F), eps=1e-12)
    cos = np.abs(np.einsum("nd,nd->n", n_src, n_tgt))  # orientation-agnostic (flipped scans)
    matched = (d <= max_distance) & (cos >= np.cos(np.radians(max_angle_deg)))
    return W, matched


def inpaint_weights(V, F, W, matched) -> np.ndarray:
    """Fill the weights of unmatched vertices by minimizing wᵀ(−L + L M⁻¹ L)w with matched fixed.

    Args:
        V: [N, 3]; F: [F, 3]; W: [N, B] (rows of unmatched vertices are ignored); matched: [N] bool.
    Returns:
        [N, B] non-negative weights summing to one.
    """
    W = np.asarray(W, np.float64).copy()
    matched = np.asarray(matched, bool)
    if matched.all():
        return _normalize(W)
    if not matched.any():
        raise ValueError("no vertex matched the source body: cannot transfer skinning weights")
    L, M = cotangent_laplacian(V, F)
    Minv = sp.diags(1.0 / M.diagonal())
    Q = (-L + L @ Minv @ L).tocsr()
    u, k = np.flatnonzero(~matched), np.flatnonzero(matched)
    Quu = Q[u][:, u].tocsc()
    rhs = -(Q[u][:, k] @ W[k])
    # Components of the target with no matched vertex make Quu singular: a tiny Tikhonov term
    # keeps the solve defined (their weights then come out ~0 and are caught below).
    Quu = Quu + sp.identity(len(u), format="csc") * 1e-10 * abs(Quu.diagonal()).mean()
    W[u] = spla.splu(Quu).solve(np.asarray(rhs))
    return _normalize(W)


def _normalize(W):
    W = np.clip(W, 0.0, None)
    s = W.sum(1, keepdims=True)
    bad = s[:, 0] < 1e-8
    if bad.any():
        raise ValueError(f"{int(bad.sum())} vertices got no skinning weight (disconnected from every matched vertex)")
    return W / s


def transfer_skinning_weights(target_V, target_F, source_V, source_F, source_W, max_distance: float = 0.03,
                              max_angle_deg: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """Robust transfer: closest-point where position and normal agree, inpainting elsewhere.

    Returns (weights [N, B], matched [N] bool).
    """
    W, matched = closest_point_transfer(target_V, target_F, source_V, source_F, source_W, max_distance,
                                        max_angle_deg)
    return inpaint_weights(target_V, target_F, W, matched), matched
