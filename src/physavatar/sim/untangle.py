"""Cloth left inside or through the body after a pinch: moved out before the next step.

A step that cannot keep the cloth outside the moving body lets the body *lag* (sim.lag). In
such a pinch the cloth is pressed to nanometres of the body (κ at its ceiling), and there
ipctk's AdditiveCCD can miss a crossing: on the CMU hop (docs/simulation.md "Session 24") a
cloth edge 5e-11 m from a body edge passed through it in a confined lag's free solve (Tight
Inclusion CCD finds the impact at t = 1.7e-5, AdditiveCCD none). From then on every step keeps
that crossing (CCD keeps whatever topology it starts from), so every later frame crosses the
body. The crease rule's release-and-pull (sim.crease) does not undo it on a moving body:
released cloth is out of body contact, so the body sweeps through it and more is released every
step (8 → 55 vertices in 5 frames, measured).

:func:`untangle` runs at the start of a step that follows a pinch (``ClothSim._crease_check``,
set by a lagging step, sim.solver): the free cloth vertices inside the body (winding number
> ½) move to 2 d̂ outside the closest point of its outer surface, and the corners of cloth edges
and triangles that cross the surface with their corners outside are lifted 2 d̂ above the
crossing (crease.crossing_cloth), for a few rounds. The result is kept only when it is
intersection-free (ipctk, against the same filter as the solve: the body and, with
self-contact, the cloth itself) with every pair apart; otherwise the start is left as it was
(and the crease rule's release-and-pull acts as before). A step without a pinch before it does
not run this: the simulation is bit-identical there.
"""

from __future__ import annotations

import logging

import numpy as np

from .crease import INSIDE, buried_vertices, crossing_cloth, grow, outside_targets, winding_numbers

log = logging.getLogger(__name__)

PINCH_DISTANCE = 1e-7  # [m] a step ending with a pair this close (1e-4 d̂) is checked at the next start too
ROUNDS = 16  # move-and-check rounds (moving a vertex out can leave a neighbour's edge through the body)


def untangle(scene, x, cloth_faces, body, body_faces, free, dhat, crease_ring: int = 1, visible: bool = False):
    """(x' [N, 3], moved vertex ids): the cloth ``x`` moved out of the ``body`` (module
    docstring), or (x, empty) when nothing is inside or through it or when the moved cloth
    would not be intersection-free. ``scene``: the solver's ContactScene ([cloth; body]);
    ``free``: bool [N], the cloth vertices that may move. ``visible``: also lift the cloth
    over the triangles next to the body's creases (those with a hidden corner) where it crosses
    their visible part (outside every other part), and move cloth inside the body to the
    closest point of any triangle where that is outside (the frame's end, untangle_frame_end:
    ipctk's check there is against every triangle, and the crease rule's steps leave cloth
    through these; docs/simulation.md "Session 25")."""
    x = np.asarray(x, np.float64)
    B = np.asarray(body, np.float64)
    Fb = np.asarray(body_faces, np.int64)
    ids = np.flatnonzero(free)
    if not len(ids) or not len(B):
        return x, np.zeros(0, np.int64)
    # the body's outer surface (without the triangles it buries in itself)
    buried = buried_vertices(B, Fb)
    hidden = np.flatnonzero(grow(buried, Fb, crease_ring)) if buried.any() else np.zeros(0, np.int64)
    outer = Fb[~np.isin(Fb, hidden).any(axis=1)] if len(hidden) else Fb
    out, moved = x.copy(), np.zeros(len(x), bool)
    for _ in range(ROUNDS):
        inside = np.zeros(len(x), bool)
        inside[ids] = winding_numbers(out[ids], B, Fb) > INSIDE
        if visible and len(hidden):
            lift = crossing_cloth(out, cloth_faces, B, Fb, dhat, visible_in=(B, Fb))
        else:
            lift = crossing_cloth(out, cloth_faces, B, outer, dhat)
        crossing = np.all(np.isfinite(lift), axis=1) & free & ~inside
        if not inside.any() and not crossing.any():
            break
        if inside.any():
            target = outside_targets(out[inside], B, Fb, hidden, dhat)
            if visible and len(hidden):  # the closest point of any triangle, where that is outside
                near = outside_targets(out[inside], B, Fb, np.zeros(0, np.int64), dhat)
                ok = winding_numbers(near, B, Fb) < INSIDE
                target[ok] = near[ok]
            out[inside] = target
        out[crossing] = lift[crossing]
        moved |= inside | crossing
    if not moved.any():
        return x, np.zeros(0, np.int64)
    X = np.vstack([out, B])
    if scene.has_intersections(X):
        log.debug("untangle: %d moved, still crossing: not kept", int(moved.sum()))
        return x, np.zeros(0, np.int64)
    scene.prepare_static(X)
    if not scene.min_distance(X) > 0.0:
        log.debug("untangle: %d moved, a pair at distance 0: not kept", int(moved.sum()))
        return x, np.zeros(0, np.int64)
    return out, np.flatnonzero(moved)


def held_body(sim, body) -> np.ndarray:
    """The body the sim holds for pose ``body``: where a lagging body got to when the last step
    was given this pose, else the pose itself."""
    B = np.asarray(body, np.float64).reshape(-1, 3)
    lag = sim._body_lag
    return lag[1] if lag is not None and np.array_equal(lag[0], B) else B


def untangle_start(sim, x, body_t, body_faces, visible: bool = False):
    """``sim.step``'s start after a pinch (``sim._crease_check``): :func:`untangle` against the
    body where the step starts (where a lagging body got to, as ``_begin_step`` continues it).
    Returns (x', number of cloth vertices moved)."""
    if not sim._crease_check or body_t is None or not len(body_t):
        return x, 0
    sim.prepare(body_t, body_faces)
    B = held_body(sim, body_t)
    scene = sim.scene
    base = getattr(scene, "base_filter", None)
    if base is not None:  # the scene's own filter (outer_surface sets this step's after)
        scene.mesh.can_collide = base
    scene.candidate_filter = None
    free = sim.inertia.unit_mass[: sim.n] > 0
    out, moved = untangle(scene, x, sim.topo.faces, B, sim._body_faces, free, sim.settings.dhat + 0.5 * sim.dmin,  # 2 d̂ beyond d_min
                          max(sim.settings.crease_ring, 0), visible)
    return out, len(moved)


def untangle_frame_end(sim, x, body, body_faces):
    """After a frame (sim.simulate), before it is written: (x', cloth vertices moved). When the
    cloth ``x`` crosses the body the sim holds (the frame's ``body``, or where a lagging body
    got to; ipctk's exact test with the scene's own filter, every body triangle, ~10 ms on the
    hop's 557 + 1,229 vertices), the next step starts with :func:`untangle`
    (``sim._crease_check``) and the cloth is untangled now (``visible``: also over the triangles
    next to the body's creases, which the check counts), so the frame is written without the
    crossing that a step's CCD missed or the crease rule let through; the next step starts from
    the untangled cloth (docs/simulation.md "Session 25"). A frame after which nothing crosses
    changes nothing."""
    if sim.scene is None or body is None or not len(body):
        return x, 0
    scene = sim.scene
    base = getattr(scene, "base_filter", None)
    if base is not None:  # the whole body (a step's outer_surface filter leaves buried triangles out)
        scene.mesh.can_collide = base
    scene.candidate_filter = None
    if not scene.has_intersections(np.vstack([x, held_body(sim, body)])):
        return x, 0
    log.debug("untangle_frame_end: the cloth crosses the body after the frame")
    sim._crease_check = True
    return untangle_start(sim, x, body, body_faces, visible=True)
