"""The cloth's contact thickness (Material.contact_offset, ipctk's d_min) estimated from a template.

A simulator with a contact thickness keeps its cloth a fixed distance off the body where it rests
on it: NVIDIA Newton's VBD at its particle radius, Codim-IPC at its thickness ξ, ipctk at d_min.
Our cloth without one comes to a fraction of d̂ of the skin. A garment draped by such a simulator
shows it: many of its free vertices lie at one distance from the body (the garment *resting* on
it), the least distance any of them has. A garment made in place with a designed clearance (the
demo dress: 5 mm at the closest, 16 mm at the 5th percentile, 62 mm at the median) has no such
band: its distances spread from the smallest on.

:func:`estimate_contact_offset` looks for that band in one frame (the template, the frame the
simulation starts from): the resting distance r is the ``percentile`` (1 %) of the free
vertices' distances to the body, and the garment rests on the body when at least
``min_fraction`` (3 %, and at least 10) of them lie within ``band`` (0.25 mm) of r. Measured
(1st percentile r; fraction within 0.25 mm): Newton's tops 6.00 mm, 16.5 %; Newton's skirt 5.98
mm, 7.1 %; the demo dress's template 9.7 mm, 0.1 %; a coarse skirt of our own simulator
(`simulate --garment skirt --edge-length 0.05`, 216 free vertices) 8.8 mm, 1.4 %. The offset is then r − d̂ (the
template starts where the barrier begins to act, d_min + d̂, and settles into it under load as it
did in the capture), capped at the least distance of any contact pair of the template plus d̂/2
(the start then needs a lift of at most about d̂ to hold every pair d̂/2 beyond it); else 0. The
cap matters: Newton's radius holds the cloth's *vertices* 6 mm off the body, while ipctk's d_min
holds every pair (body vertices against cloth faces, edges against edges), and on Newton's drapes
those come to 2.5 mm. On the foreign captures 3 mm (the cap) predicted the held-out motion best of
0, 2, 3, 4 and 5 mm; 5 mm (195 start vertices lifted up to 3.5 mm, :func:`lift_start`) was worse
than none (docs/physics.md, "Session 25").

ipctk's barrier is b(d² − d_min², (2 d_min + d̂) d̂), undefined for d < d_min (NaN energies, and a
Hessian that cannot be projected onto the PSD cone: why ``SimSettings.dmin`` failed before), so
every cloth–body primitive pair of the start must lie beyond it, not only the vertices: Newton's
cloth keeps its *vertices* 6 mm off the body, but body vertices and edges come to 2.5 mm of its
faces and edges. For a thickness given or a start other than the template, :func:`lift_start`
moves the cloth vertices of such pairs out to d_min + d̂/2 (ipctk's pairs and distance gradients);
:func:`feasible_start` does that and, where it cannot, lowers the thickness to what the start
allows.
"""

from __future__ import annotations

import numpy as np

PERCENTILE = 1.0  # % of the free vertices: the resting distance r (robust to a few outliers)
BAND = 2.5e-4  # m: a vertex within this of r rests on the body
MIN_FRACTION = 0.03  # of the free vertices within the band (and at least MIN_COUNT): it rests on the body
MIN_COUNT = 10
LIFT = 1.0  # × d̂: the estimate needs the start lifted by at most about this (its cap)


def estimate_contact_offset(vertices, faces, body_vertices, body_faces, boundary=(), dhat: float = 1e-3,
                            percentile: float = PERCENTILE, band: float = BAND,
                            min_fraction: float = MIN_FRACTION) -> tuple[float, dict]:
    """The contact thickness [m] of a garment ``vertices`` [N, 3] (triangles ``faces``) resting on
    a body (``body_vertices`` [Nb, 3], ``body_faces``), from its free vertices (not in
    ``boundary``) outside the body (module docstring). Returns (offset, report) with the report's
    resting distance, band fraction, the start's least pair distance and the cap, in mm."""
    from ..geometry.closest import MeshQuery

    V = np.asarray(vertices, np.float64)
    B = np.asarray(body_vertices, np.float64)
    free = np.ones(len(V), bool)
    free[np.asarray(boundary, np.int64)] = False
    d = MeshQuery(B, np.asarray(body_faces, np.int64)).signed_distance(V[free])[0]
    d = d[d > 0]
    report = {"method": "template resting band", "percentile": percentile, "band_mm": 1e3 * band,
              "min_fraction": min_fraction, "dhat_mm": 1e3 * dhat}
    if len(d) < 10:
        return 0.0, report | {"offset_mm": 0.0, "resting": False, "why": "fewer than 10 free vertices outside the body"}
    r = float(np.percentile(d, percentile))
    frac = float(np.mean(d <= r + band))
    resting = frac >= min_fraction and np.count_nonzero(d <= r + band) >= MIN_COUNT
    offset = max(r - dhat, 0.0) if resting else 0.0
    report |= {"resting_mm": 1e3 * r, "band_fraction": frac, "resting": bool(resting)}
    if offset > 0:  # no more than the template allows with a lift of at most d̂ (feasible_start)
        least = start_distance(V, faces, B, body_faces, boundary)
        cap = least + LIFT * dhat - 0.5 * dhat
        report |= {"least_pair_mm": 1e3 * least, "cap_mm": 1e3 * cap}
        offset = min(offset, cap)
    return offset, report | {"offset_mm": 1e3 * offset}


def lift_start(vertices, faces, body_vertices, body_faces, clearance: float, fixed=(), rounds: int = 20,
               limit: float = 0.01):
    """``vertices`` [N, 3] with every contact pair of cloth and body at least ``clearance`` [m]
    apart, moving free cloth vertices only (not ``fixed``): each round, the cloth vertices of every
    pair closer than that (ipctk's pairs: vertex–face, edge–edge, ... both ways) move along the
    pair's distance gradient by 1.1 × the shortfall, at most ``limit`` in all. A start that a
    contact thickness needs (ipctk's barrier is undefined within d_min): a simulator without one
    (NVIDIA Newton's particles) lets the body's vertices and edges come closer to the cloth's
    faces and edges than its vertices. Returns (vertices, least pair distance after [m])."""
    from .contact import ContactScene

    x0 = np.asarray(vertices, np.float64)
    x = x0.copy()
    B = np.asarray(body_vertices, np.float64)
    n = len(x)
    free = np.ones(n, bool)
    free[np.asarray(fixed, np.int64)] = False
    scene = ContactScene(x, faces, B, body_faces, dhat=clearance, prescribed=np.asarray(fixed, np.int64))
    E, F = scene.mesh.edges, scene.mesh.faces
    for _ in range(rounds):
        X = np.vstack([x, B])
        scene.prepare_static(X)
        c = scene.collisions_at(X)
        move = np.zeros_like(x)
        for group in (c.vv_collisions, c.ev_collisions, c.ee_collisions, c.fv_collisions):
            for col in group:
                ids = np.array(col.vertex_ids(E, F))
                ids = ids[ids >= 0]
                d = float(np.sqrt(max(col.compute_distance(X[ids].ravel()), 0.0)))
                if d >= clearance:
                    continue
                g = np.asarray(col.compute_distance_gradient(X[ids].ravel())).reshape(-1, 3)
                cloth = (ids < n) & free[np.minimum(ids, n - 1)]
                if not cloth.any():
                    continue
                dirs = g[cloth] / np.maximum(np.linalg.norm(g[cloth], axis=1, keepdims=True), 1e-30)
                step = 1.1 * (clearance - d) * dirs
                for i, v in zip(ids[cloth], step):
                    if np.dot(v, v) > np.dot(move[i], move[i]):
                        move[i] = v
        if not move.any():
            break
        x = x + move
        total = np.linalg.norm(x - x0, axis=1)
        over = total > limit
        if over.any():  # never more than ``limit`` from the start
            x[over] = x0[over] + (x - x0)[over] * (limit / total[over])[:, None]
    return x, start_distance(x, faces, B, body_faces, fixed)


def start_distance(vertices, faces, body_vertices, body_faces, prescribed=(), reach: float = 0.05) -> float:
    """The least distance [m] between the cloth and the body over every primitive pair that the
    simulation's contact sees (ipctk; pairs of prescribed cloth vertices and the body left out, as
    in sim.contact.ContactScene); ``reach`` when none is closer."""
    from .contact import ContactScene

    scene = ContactScene(vertices, faces, body_vertices, body_faces, dhat=reach,
                         prescribed=np.asarray(prescribed, np.int64))
    X = np.vstack([vertices, body_vertices]).astype(np.float64)
    scene.prepare_static(X)
    c = scene.collisions_at(X)
    if not len(c):
        return reach
    return float(np.sqrt(c.compute_minimum_distance(scene.mesh, X)))


def feasible_start(vertices, faces, body_vertices, body_faces, offset: float, dhat: float, fixed=()):
    """(start, thickness, report): ``vertices`` lifted so that every contact pair is d̂/2 beyond
    ``offset`` (:func:`lift_start`), and the offset, lowered to the least pair distance less d̂/2
    where the lift could not reach it (the vertices unchanged when nothing was closer)."""
    need = offset + 0.5 * dhat
    least0 = start_distance(vertices, faces, body_vertices, body_faces, fixed)
    report = {"least_pair_mm": 1e3 * least0, "lifted_vertices": 0, "max_lift_mm": 0.0}
    if offset <= 0 or least0 >= need - 0.1 * dhat:  # (the estimate's cap sits at need itself)
        return np.asarray(vertices, np.float64), offset, report
    x, least = lift_start(vertices, faces, body_vertices, body_faces, need * 1.02, fixed)
    lift = np.linalg.norm(x - np.asarray(vertices), axis=1)
    thickness = offset if least >= need - 0.1 * dhat else max(least - 0.5 * dhat, 0.0)
    report.update(lifted_vertices=int(np.count_nonzero(lift > 0)), max_lift_mm=1e3 * float(lift.max()),
                  least_pair_after_mm=1e3 * least, thickness_mm=1e3 * thickness)
    return x, thickness, report
