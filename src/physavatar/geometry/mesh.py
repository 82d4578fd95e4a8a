"""Triangle-mesh basics: vertex normals, edges, adjacency, sub-meshes, quality figures (numpy only)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, eps: float = 1e-30) -> np.ndarray:
    """Area-weighted unit vertex normals: [..., V, 3] for vertices [..., V, 3], faces [F, 3].

    Each vertex sums the (2·area-scaled) normals of its faces and is divided by the sum's length,
    or by ``eps`` where that is shorter (a vertex on no face gets a zero normal). The result has
    the dtype of ``vertices``.
    """
    V = np.asarray(vertices)
    F = np.asarray(faces)
    if V.ndim > 2:
        flat = V.reshape(-1, V.shape[-2], 3)
        return np.stack([vertex_normals(x, F, eps) for x in flat]).reshape(V.shape)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n = np.zeros_like(V)
    for k in range(3):
        np.add.at(n, F[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), eps)


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """[E, 2] unique undirected edges (i < j) of a triangle mesh, sorted."""
    F = np.asarray(faces)
    return np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)


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


def mesh_quality(V: np.ndarray, F: np.ndarray) -> dict:
    """Angles (degrees), the largest/smallest area ratio, the mean edge length and the counts."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)

    def ang(p, q, r):
        u, v = q - p, r - p
        cosv = (u * v).sum(1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
        return np.degrees(np.arccos(np.clip(cosv, -1, 1)))

    angles = np.c_[ang(a, b, c), ang(b, c, a), ang(c, a, b)]
    edges = mesh_edges(F)
    el = np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1)
    return {"min_angle_deg": float(angles.min()), "max_angle_deg": float(angles.max()),
            "area_ratio": float(area.max() / area.min()), "mean_edge": float(el.mean()),
            "n_vertices": int(len(V)), "n_faces": int(len(F))}
