"""Intersection counts between two triangle meshes (ipctk's exact edge-triangle test)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .mesh import mesh_edges


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
