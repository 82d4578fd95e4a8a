"""Intersection counts between two triangle meshes (ipctk's exact edge-triangle test)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .mesh import mesh_edges


def _edge_triangle_pairs(EV, E, TV, T) -> list[tuple[int, int]]:
    """(edge of mesh 1, triangle of mesh 2) pairs that intersect (ipctk's exact test on
    candidates whose bounding spheres overlap)."""
    import ipctk

    a, b = EV[E[:, 0]], EV[E[:, 1]]
    mid, r_e = 0.5 * (a + b), 0.5 * np.linalg.norm(b - a, axis=1)
    tri = TV[T]
    cen = tri.mean(1)
    r_t = np.linalg.norm(tri - cen[:, None], axis=2).max(1)
    tree = cKDTree(cen)
    lists = tree.query_ball_point(mid, r_e + r_t.max())
    pairs = []
    for i, cand in enumerate(lists):
        if not cand:
            continue
        cand = np.asarray(cand)
        cand = cand[np.linalg.norm(cen[cand] - mid[i], axis=1) <= r_e[i] + r_t[cand]]
        for t in cand:
            if ipctk.is_edge_intersecting_triangle(a[i], b[i], tri[t, 0], tri[t, 1], tri[t, 2]):
                pairs.append((i, int(t)))
    return pairs


def intersecting_pairs(V1, F1, V2, F2) -> tuple[list[tuple[np.ndarray, int]], list[tuple[np.ndarray, int]]]:
    """The crossings between two meshes, both ways: ([(edge of mesh 1 as its two vertex ids,
    triangle of mesh 2)], [(edge of mesh 2, triangle of mesh 1)])."""
    V1, V2, F1, F2 = np.asarray(V1, float), np.asarray(V2, float), np.asarray(F1), np.asarray(F2)
    E1, E2 = mesh_edges(F1), mesh_edges(F2)
    return ([(E1[e], t) for e, t in _edge_triangle_pairs(V1, E1, V2, F2)],
            [(E2[e], t) for e, t in _edge_triangle_pairs(V2, E2, V1, F1)])


def count_intersections(V1, F1, V2, F2, fixed=None) -> int:
    """Intersecting edge-triangle pairs between two meshes, both ways (0: the surfaces are apart).

    ``ipctk.has_intersections`` on the union cannot be used here: the Anny body intersects itself
    in its rest pose (fingers, armpits), so only pairs across the two meshes are tested.

    ``fixed`` [K] (vertex ids of mesh 1 whose motion is prescribed, e.g. a garment's boundary on
    the body mesh 2): a crossing whose mesh-1 edge or triangle has only fixed vertices is not
    counted. The simulator never sees such a pair (``sim.contact.prescribed_filter``: no contact
    between prescribed vertices and the body), and nothing can move it out.
    """
    if fixed is not None:
        g, b = _movable(*intersecting_pairs(V1, F1, V2, F2), F1, fixed, len(V1))
        return len(g) + len(b)
    V1, V2 = np.asarray(V1, float), np.asarray(V2, float)
    return (len(_edge_triangle_pairs(V1, mesh_edges(F1), V2, np.asarray(F2)))
            + len(_edge_triangle_pairs(V2, mesh_edges(F2), V1, np.asarray(F1))))


def _movable(edges_1, edges_2, F1, fixed, n: int):
    """The crossings of :func:`intersecting_pairs` (``edges_1``: mesh-1 edges through mesh-2
    triangles; ``edges_2``: mesh-2 edges through mesh-1 triangles) less those whose mesh-1
    primitive has only ``fixed`` vertices (None: all kept); ``n`` mesh 1's vertex count."""
    if fixed is None:
        return edges_1, edges_2
    F1 = np.asarray(F1)
    fix = np.zeros(n, bool)
    fix[np.asarray(fixed, dtype=np.int64)] = True
    return ([(e, t) for e, t in edges_1 if not fix[e].all()],
            [(e, t) for e, t in edges_2 if not fix[F1[t]].all()])


def push_out_crossings(V, F, body_V, body_F, step: float, fixed=None, iters: int = 10) -> tuple[np.ndarray, int]:
    """Move a garment (V, F) out of the body surfaces it crosses, where a vertex-wise push cannot
    see it: a body edge through a garment triangle whose corners all lie outside the body (a
    coarse collider's ridge), or a garment edge through a body triangle between its vertices.

    Each iteration moves the corners of every crossing garment edge or triangle by ``step`` along
    the body's outward normal there (the crossed body triangle's, or the crossing body edge's
    vertex normals), their neighbours half as far so the cloth stays smooth; ``fixed`` vertices
    (boundary targets) stay, and crossings made only of them are neither pushed nor counted
    (:func:`count_intersections`). Returns the new vertices and the number of crossing pairs left
    after ``iters`` iterations (0: apart).
    """
    from .mesh import adjacency, vertex_normals

    V, F = np.array(V, float), np.asarray(F)
    body_V, body_F = np.asarray(body_V, float), np.asarray(body_F)
    fn = np.cross(body_V[body_F[:, 1]] - body_V[body_F[:, 0]], body_V[body_F[:, 2]] - body_V[body_F[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    vn = vertex_normals(body_V, body_F)
    A = adjacency(F, len(V))
    free = np.ones(len(V), bool)
    if fixed is not None:
        free[np.asarray(fixed, dtype=np.int64)] = False
    for _ in range(iters):
        garment_edges, body_edges = _movable(*intersecting_pairs(V, F, body_V, body_F), F, fixed, len(V))
        if not garment_edges and not body_edges:
            return V, 0
        direction = np.zeros_like(V)
        for edge, t in garment_edges:
            direction[edge] += fn[t]
        for edge, t in body_edges:
            direction[F[t]] += vn[edge].sum(0)
        norm = np.linalg.norm(direction, axis=1)
        moved = (norm > 0) & free
        delta = np.zeros_like(V)
        delta[moved] = step * direction[moved] / norm[moved, None]
        spread = (A @ delta) / np.maximum(A @ moved.astype(float), 1.0)[:, None]
        V += np.where(moved[:, None], delta, 0.5 * spread * free[:, None])
    garment_edges, body_edges = _movable(*intersecting_pairs(V, F, body_V, body_F), F, fixed, len(V))
    return V, len(garment_edges) + len(body_edges)
