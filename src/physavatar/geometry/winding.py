"""Generalised winding number (Jacobson et al. 2013) of a triangle mesh at query points: the sum
of the triangles' signed solid angles (Van Oosterom & Strackee 1983) over 4π. Exact, O(N·F): 1
inside a closed outward-oriented mesh, 0 outside, 2 where two of its parts overlap, fractional
near holes. One numba per-point function, looped over the points serially (the simulator's
per-step test, ``sim.crease``: on a shared 2-core machine a parallel loop costs more than it
saves) or in parallel (``metrics.winding_number`` over whole sequences)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np


def winding_number(points, vertices, faces, vertex_ids=None, *, parallel: bool = False) -> np.ndarray:
    """[M] winding number of the mesh (vertices [V, 3], faces [F, 3]) at points [M, 3]. A point
    that is mesh vertex ``vertex_ids[i]`` (≥ 0) leaves out its own triangles (they subtend no
    solid angle from it, but their formula is 0/0 there)."""
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    F = np.ascontiguousarray(np.asarray(faces, dtype=np.int64).reshape(-1, 3))
    if not len(p) or not len(F):
        return np.zeros(len(p))
    tri = np.ascontiguousarray(np.asarray(vertices, dtype=np.float64)[F])
    skip = np.full(len(p), -1, np.int64) if vertex_ids is None else np.asarray(vertex_ids, np.int64).reshape(-1)
    if len(skip) != len(p):
        raise ValueError(f"vertex_ids has {len(skip)} entries for {len(p)} points")
    return _kernels()[bool(parallel)](p, tri, skip, F)


@lru_cache(maxsize=1)
def _kernels():
    import numba

    @numba.njit(cache=True, fastmath=False)
    def at_point(px, py, pz, k, tri, faces):  # pragma: no cover - compiled
        total = 0.0
        for f in range(tri.shape[0]):
            if k >= 0 and (faces[f, 0] == k or faces[f, 1] == k or faces[f, 2] == k):
                continue
            ax, ay, az = tri[f, 0, 0] - px, tri[f, 0, 1] - py, tri[f, 0, 2] - pz
            bx, by, bz = tri[f, 1, 0] - px, tri[f, 1, 1] - py, tri[f, 1, 2] - pz
            cx, cy, cz = tri[f, 2, 0] - px, tri[f, 2, 1] - py, tri[f, 2, 2] - pz
            la = np.sqrt(ax * ax + ay * ay + az * az)
            lb = np.sqrt(bx * bx + by * by + bz * bz)
            lc = np.sqrt(cx * cx + cy * cy + cz * cz)
            det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
            den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc
                   + (bx * cx + by * cy + bz * cz) * la + (cx * ax + cy * ay + cz * az) * lb)
            total += np.arctan2(det, den)
        return total / (2.0 * np.pi)

    @numba.njit(cache=True)
    def serial(p, tri, skip, faces):  # pragma: no cover - compiled
        out = np.empty(p.shape[0])
        for i in range(p.shape[0]):
            out[i] = at_point(p[i, 0], p[i, 1], p[i, 2], skip[i], tri, faces)
        return out

    @numba.njit(cache=True, parallel=True)
    def parallel(p, tri, skip, faces):  # pragma: no cover - compiled
        out = np.empty(p.shape[0])
        for i in numba.prange(p.shape[0]):
            out[i] = at_point(p[i, 0], p[i, 1], p[i, 2], skip[i], tri, faces)
        return out

    return {False: serial, True: parallel}
