"""Confined lag: when a step's penalty phase gives up, only the body near the pinch lags.

The kinematic-penalty phase (:func:`penalty_phase`, called by solver.ClothSim._newton) moves every prescribed vertex
(the body, the Dirichlet cloth vertices) with one line-search step length, so a single pinch —
cloth caught where Anny's collider passes through itself (the groin, the back of the knee:
docs/simulation.md "Why the whole clips stalled") — holds back the whole body: on the CMU walk
one pinch at the groin left every body vertex 16 mm, then 104, then 194 mm behind its pose.

:func:`confine_lag` runs when such a phase gives up (SimSettings.lag_radius > 0). It carries
the cloth with the body to its pose (start.follow_body, CCD-checked legs). Where a leg is cut,
the collision candidates of that leg with a time of impact below 1 (ipctk's narrow-phase CCD
per candidate) name the pinch: their prescribed vertices are *held back*. Every prescribed
vertex then gets a lag fraction that is 1 within ``lag_radius`` of a held-back one and falls
linearly to 0 at twice that distance, and the carry is tried again to that partial pose: the
rest of the body reaches its pose. A leg cut again holds back the vertices of its pairs too
(another pinch), or, when they are held already, doubles the radius; after ``LAG_ROUNDS``
carries the whole body lags as before. The solver then finishes
the step with the prescribed vertices fixed where they are (the free system); the step still
reports its lag (StepStats.body_gap, the largest distance from the pose), and the next step
starts from where the body got to (ClothSim._body_lag), as before.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .start import follow_body

log = logging.getLogger(__name__)
LAG_ROUNDS = 8  # carries tried (more held-back vertices or a wider radius each) before the whole body lags


def blocked_vertices(scene, X0, X1) -> np.ndarray:
    """The vertex ids of every collision candidate of the straight move X0 → X1 (stacked
    [cloth; body]) whose time of impact is below 1 (ipctk's AdditiveCCD per candidate, as the
    scene's CCD)."""
    scene.prepare_segment(X0, X1)
    E, F = scene.mesh.edges, scene.mesh.faces
    out = set()
    cands = scene.candidates
    for group in (cands.vv_candidates, cands.ev_candidates, cands.ee_candidates, cands.fv_candidates):
        for c in group:
            ids = [i for i in c.vertex_ids(E, F) if i >= 0]
            hit, toi = c.ccd(X0[ids].ravel(), X1[ids].ravel(), scene.dmin, 1.0, scene.ccd)
            if hit and toi < 1.0:
                out.update(ids)
    return np.array(sorted(out), dtype=np.int64)


def lag_weights(points, seeds, radius: float) -> np.ndarray:
    """Per point [M, 3]: 1 within ``radius`` of the nearest of ``seeds`` [S, 3], falling
    linearly to 0 at twice the radius."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(seeds).query(points)
    return np.clip(2.0 - d / radius, 0.0, 1.0)


def confine_lag(sim, sv, stats) -> bool:
    """After a penalty phase gave up at ``sv.X``: move the prescribed vertices away from the
    pinch to their targets, carrying the cloth (module docstring). True when it did (then
    ``sv.X`` holds the new state and ``sv.penalty`` is False), False when the whole body lags."""
    s = sim.settings
    if s.follow_body <= 0:  # the carry is off: the whole body lags
        return False
    K, target = sim.penalty.kinematic, sim.penalty.target
    X = sv.X
    goal = X.copy()
    goal[K] = target
    free = sim.inertia.unit_mass[: sim.n] > 0
    radius, reached = s.lag_radius, False
    seeds = np.zeros(0, dtype=np.int64)  # the prescribed vertices held back (and their radius)
    w = np.zeros((len(K), 1))
    for _ in range(LAG_ROUNDS):
        if len(seeds):
            w = lag_weights(X[K], X[seeds], radius)[:, None]
        if np.all(w == 1.0):  # every prescribed vertex is held back: nothing to confine
            break
        part = goal.copy()
        part[K] = np.where(w == 0.0, target, X[K] + (1.0 - w) * (target - X[K]))  # (exactly X where w = 1)
        cut = []
        X_f, reached = follow_body(sim.scene, sim._body_faces, free, s, X, part, None, stats, lift_still=False, cut=cut)
        if reached:
            break
        # the carry was cut: hold back the prescribed vertices of the pairs that cut it (a
        # pinch), or, when those are held already, widen the radius
        more = np.setdiff1d(np.intersect1d(blocked_vertices(sim.scene, *cut[0]), K), seeds)
        if len(more):
            seeds = np.union1d(seeds, more)
        else:
            radius *= 2.0
    if not reached or np.all(w == 1.0):
        log.debug("confine_lag: %d blocked, the whole body lags", len(seeds))
        sim.scene.prepare_static(X)
        return False
    log.debug("confine_lag: %d blocked, radius %.3f m, %d of %d held back", len(seeds), radius,
              int(np.sum(w > 0)), len(K))
    sv.X, sv.penalty, sv.confined = X_f, False, True
    sim.scene.prepare_static(sv.X)
    sim.friction.lag(sv.X, sim.barrier)
    stats.lag_radius = radius
    return True


def penalty_phase(sim, sv, stats):
    """The kinematic-penalty phase of ``sim`` (solver.ClothSim) after a penalty-mode iteration of
    its solve ``sv``: snap the prescribed vertices to their targets once
    they are close and the rest of the move is collision-free (back to the free system),
    retry carrying the cloth with the body, or stiffen the penalty when the targets stall.
    Returns "break" (give up: the body lags), "continue" (next iteration at once) or None."""
    s, X = sim.settings, sv.X
    sv.penalty_iters += 1
    gap = np.max(np.abs(X[sim.penalty.kinematic] - sim.penalty.target))
    sv.gaps.append(gap)
    if sim.stall_exit and gap >= 1e-2 * s.dhat and len(sv.gaps) > sim.stall_window:
        if gap > (1 - sim.stall_progress) * sv.gaps[~sim.stall_window]:  # a pinch: shorter steps do better
            return "break"
    if gap < 1e-2 * s.dhat:
        X_snap = X.copy()
        X_snap[sim.penalty.kinematic] = sim.penalty.target
        tcd = time.perf_counter()
        ok = sim.scene.collision_free_stepsize(X, X_snap) >= 1.0
        stats.time["ccd"] += time.perf_counter() - tcd
        if ok:
            sv.X = X_snap
            sv.penalty = False
            sim.scene.prepare_static(sv.X)
            sim.friction.lag(sv.X, sim.barrier)
        else:
            # The cloth sits closer to the body than the body's remaining gap: the barrier
            # holds the body short of its target at this penalty weight, and more
            # iterations at the same weight do not move it. A stiffer penalty pushes the
            # cloth on.
            sim.penalty.weight *= 10.0
            if sv.penalty_iters >= s.max_penalty_iterations:
                return "break"
            return "continue"
    elif s.follow_body > 0 and sim.nb and s.follow_retry > 0 and sv.penalty_iters % s.follow_retry == 0:
        # try again to carry the cloth the rest of the way (the pairs that cut the
        # first try may have separated)
        free = sim.inertia.unit_mass[: sim.n] > 0
        X_f, reached = follow_body(sim.scene, sim._body_faces, free, s, X, sv.X_goal, None, stats)
        sim.scene.prepare_static(X_f if reached else X)
        if reached:
            sv.X = X_f
            sv.penalty = False
            stats.body_follows += 1
            sim.friction.lag(sv.X, sim.barrier)
    if sv.penalty and sv.penalty_iters >= s.max_penalty_iterations:
        return "break"  # no room for the cloth at the body's pose: keep what was reached
    if sv.penalty and sv.penalty_iters % 10 == 0:
        sim.penalty.weight *= 10.0  # AL-style escalation when targets stall
        return "continue"
    return None
