"""A collider's own collapse undone: vertices buried in the body moved out onto its outer surface.

Linear blend skinning folds a joint's crease into the limb: on the CMU hop the back of the left
knee sinks 24 mm into the leg at one frame (docs/simulation.md "Session 23", "Session 26"), and
the triangles around the buried vertices form a pit whose visible walls converge inside the
limb. Cloth drawn into it has no intersection-free place at the body's pose (the step lags), and
the crease rule (sim.crease), which lets it through the buried triangles, leaves it crossing the
body.

:func:`uncollapse` moves every buried vertex (winding number of the body mesh above
``crease.BURIED``: inside another part) to the closest point of the body's outer surface (its
triangles without a buried corner or a corner one ring from one), ``offset`` outside along that
triangle's normal, and repeats while a vertex is still buried (a moved vertex can bury a
neighbour's triangle). The surface the cloth then meets is the union's outer skin at the crease,
without the pit. A body without buried vertices is returned as it is (the same array). ``sim.simulate`` keeps a
frame simulated on the uncollapsed body only when its cloth does not cross the body as given
(:func:`crosses`); otherwise the crease rule follows on the given body, as before.
"""

from __future__ import annotations

import numpy as np

from .crease import buried_vertices, grow

ROUNDS = 4
OFFSET = 1e-4  # [m] outside the outer surface (a vertex exactly on it reads as half buried)


def uncollapse(vertices, faces, offset: float = OFFSET, near=None):
    """(vertices' [V, 3], moved ids): ``vertices`` with the buried ones moved out (module
    docstring); ``near``: bool [V], only these are tested (default all)."""
    from ..geometry.closest import MeshQuery

    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    out, moved = V, np.zeros(len(V), bool)
    for _ in range(ROUNDS):
        bur = buried_vertices(out, F, near)
        if not bur.any():
            break
        hidden = grow(bur, F, 1)
        outer = F[~hidden[F].any(axis=1)]
        tri = out[outer]
        area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        outer = outer[area > 1e-12]  # (vertices moved onto one point make triangles without a normal)
        if not len(outer):
            break
        ids = np.flatnonzero(bur)
        _, face, _, q = MeshQuery(out, outer, spacing=0.02).closest(out[ids])
        tri = out[outer[face]]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        ok = np.all(np.isfinite(q), axis=1)
        if not ok.any():
            break
        ids, q, n = ids[ok], q[ok], n[ok]
        out = out.copy() if out is V else out
        out[ids] = q + offset * n
        moved[ids] = True
    return out, np.flatnonzero(moved)


def crosses(sim, x, body) -> bool:
    """Whether the cloth ``x`` crosses ``body`` (ipctk's exact test with the sim's scene and its own
    filter, every body triangle: the check ``stages.simulate`` makes on the written frame)."""
    scene = sim.scene
    base = getattr(scene, "base_filter", None)
    if base is not None:  # (a crease step's filter leaves buried triangles out)
        scene.mesh.can_collide = base
    scene.candidate_filter = None
    return bool(scene.has_intersections(np.vstack([x, np.asarray(body, np.float64)])))
