"""Line-search helpers of the Newton solve (solver.ClothSim._line_search)."""

from __future__ import annotations

import time

import numpy as np

from .contact import ContactScene


class CandidateScene(ContactScene):
    """A ContactScene that remembers, per coordinate, the box of the configurations its last
    candidate build covered (the configuration of a static build; the two ends of a segment's).

    ipctk's broad phase bounds each primitive by the box of its vertices at the build's
    configuration(s), inflated by d̂; a configuration X inside that box per vertex has every
    primitive box inside the built one, so the candidates hold every pair within d̂ at X and
    its barrier set needs no new build (:meth:`covers`). The solver asks this where it used to
    rebuild around a point a CCD segment or a carry had just swept (docs/simulation.md
    "Session 17")."""

    _box = None

    def prepare_static(self, X):
        super().prepare_static(X)
        self._box = (np.array(X, dtype=np.float64), None)

    def prepare_segment(self, X0, X1):
        super().prepare_segment(X0, X1)
        self._box = (np.minimum(X0, X1), np.maximum(X0, X1))

    def covers(self, X) -> bool:
        """Whether the last build's candidates hold every pair within d̂ at X."""
        box = self._box
        if box is None or np.shape(X) != box[0].shape:
            return False
        if box[1] is None:
            return bool(np.array_equal(X, box[0]))
        return bool(np.all(X >= box[0]) and np.all(X <= box[1]))


class EnergyMemo:
    """E at the last accepted iterate, reused as the next line search's E(X) while nothing E
    depends on has changed: the iterate (the same array), the barrier set at it (ContactScene's
    cached collisions, rebuilt after any new candidate build), the barrier potential (a new one
    at every κ change), the lagged friction set, the penalty mode and weight. The value is then
    the same bits that E(X) would return (docs/simulation.md "Session 17")."""

    def __init__(self):
        self._key = None
        self.value = None

    @staticmethod
    def key(sim, X, penalty):
        return ((X, sim.scene._collisions_at, sim.barrier.potential, sim.friction.tangential),
                (bool(penalty), sim.penalty.weight))

    def get(self, key):
        if self._key is None or self._key[1] != key[1] or any(a is not b for a, b in zip(self._key[0], key[0])):
            return None
        return self.value

    def set(self, key, value):
        self._key, self.value = key, value


def backtrack(scene, energy, X, step, stats, E0=None):
    """(X_new, E(X_new), α): X + α·step with α the collision-free step size (CCD), halved
    until E does not increase (or α < 1e-12). ``scene.covers_last_point`` is set: X_new lies
    on the CCD's segment, whose candidates hold its barrier set. ``E0``: E(X) when known
    (EnergyMemo), else computed here."""
    tls = time.perf_counter()
    # E at X before the CCD's segment build replaces the candidates: the barrier set at X is
    # still the one the gradient used (no rebuild)
    if E0 is None:
        E0 = energy(X)
    stats.time["line_search"] += time.perf_counter() - tls
    tcd = time.perf_counter()
    alpha = scene.collision_free_stepsize(X, X + step)
    scene.covers_last_point = True  # X + α step, α ≤ 1, lies on this segment
    stats.time["ccd"] += time.perf_counter() - tcd
    tls = time.perf_counter()
    while True:
        X_new = X + alpha * step
        E1 = energy(X_new)
        if E1 <= E0 or alpha < 1e-12:
            break
        alpha *= 0.5
        stats.line_search_iterations += 1
    stats.time["line_search"] += time.perf_counter() - tls
    return X_new, E1, alpha


def expand_step(scene, energy, X, step, X_new, E_new, stats, max_scale=64.0):
    """Try X + 2·step, 4·step, ... while the energy keeps decreasing; a move that CCD cuts is
    tried at its collision-free fraction and ends the search. Returns the best point.

    ``scene``: the ContactScene (its CCD; ``covers_last_point`` is kept up to date);
    ``energy(X)``: E at X (free system); (X_new, E_new): the accepted full step and its energy.

    Projected Newton converges only linearly along a mode whose curvature the PSD
    projection overstates: e.g. a vertex sliding over a body vertex, where the barrier's
    negative tangential curvature is clamped away. The full step is then accepted every
    iteration while the residual shrinks by a constant ratio close to 1 (docs/simulation.md
    "The step"). Doubling the step along that direction reaches the same minimiser in a few
    energy evaluations; the stopping rule is unchanged.
    """
    scale = 1.0
    while scale < max_scale:
        X_try = X + (2.0 * scale) * step
        tc = time.perf_counter()
        a = scene.collision_free_stepsize(X, X_try)
        stats.time["ccd"] += time.perf_counter() - tc
        last = a < 1.0  # the doubled step is cut by CCD: take its collision-free part, stop
        if last:
            if 2.0 * scale * a <= scale * 1.05:
                # that segment (ending at 2·scale·a·step) may stop short of X_new
                scene.covers_last_point = 2.0 * scale * a >= scale
                break
            X_try = X + (2.0 * scale * a) * step
        E_try = energy(X_try)
        if not E_try < E_new:
            break
        scale = 2.0 * scale * a if last else 2.0 * scale
        X_new, E_new = X_try, E_try
        stats.step_expansions += 1
        if last:
            break
    return X_new
