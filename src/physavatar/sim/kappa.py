"""The barrier stiffness κ of a step's Newton solve (solver.ClothSim), as IPC adapts it.

ipctk's initial κ from the balance of elastic and barrier gradients (IPC Sec. 4.3), and its
update when contacts keep closing in. κ persists across steps (``ClothSim.barrier_stiffness``,
``max_barrier_stiffness``, ``_kappa_balanced``; ``ClothSim.get_state`` saves them).
"""

from __future__ import annotations

import time

import ipctk
import numpy as np


def initial_stiffness(sim, X):
    """Set ``sim``'s κ from the gradient balance at X, unless it is balanced already.

    Before any contact κ is ipctk's minimum (scaled by mass); the first time contacts
    exist it is set from the gradient balance; afterwards it only grows through
    :func:`adapt_stiffness` and persists across steps, as in IPC.
    """
    if sim._kappa_balanced:
        return
    c = sim.scene.collisions_at(X)
    if sim.barrier_stiffness > 0 and not len(c):
        return
    s = sim.settings
    grad_e = np.sum([t.gradient(X) for t in sim.terms], axis=0)
    unit = ipctk.BarrierPotential(s.dhat, 1.0)
    grad_b = unit.gradient(c, sim.scene.mesh, X) if len(c) else np.zeros_like(grad_e)
    k, kmax = ipctk.initial_barrier_stiffness(
        sim.scene.bbox_diagonal(X), unit.barrier, s.dhat, sim._average_mass,
        grad_e, grad_b, s.barrier_stiffness_scale, sim.dmin,
    )
    sim._kappa_balanced = bool(len(c))
    sim.barrier_stiffness = max(k, sim.barrier_stiffness)
    sim.max_barrier_stiffness = max(kmax, sim.max_barrier_stiffness)
    sim.barrier.set_stiffness(sim.barrier_stiffness)


def adapt_stiffness(sim, sv, stats):
    """ipctk's adaptive κ after a Newton iteration (``sv``: the solve's state, solver._Solve):
    grow it when contacts keep closing in."""
    tc = time.perf_counter()
    min_dist = sim.scene.min_distance(sv.X)
    if sim.max_barrier_stiffness > 0 and np.isfinite(min_dist) and np.isfinite(sv.prev_min_dist):
        k = ipctk.update_barrier_stiffness(sv.prev_min_dist, min_dist, sim.max_barrier_stiffness,
                                           sim.barrier_stiffness, sv.diag, dmin=sim.dmin)
        if k != sim.barrier_stiffness:
            sim.barrier_stiffness = k
            sim.barrier.set_stiffness(k)
    sv.prev_min_dist = min_dist
    stats.time["contact"] += time.perf_counter() - tc
