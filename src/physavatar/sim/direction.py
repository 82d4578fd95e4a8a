"""Shaping a Newton direction of the step (solver.ClothSim._newton_direction) near contact.

IPC's log barrier has no curvature at d̂ (b''(d̂) = 0), so the Newton model of a cloth–body
pair at a fraction of a millimetre barely sees it: the direction carries the cloth through the
body, and CCD cuts the *whole* step to ~10 % of that pair's gap (α = 0.03–0.4 on the demo
walk, ~20 iterations a frame; docs/simulation.md "Session 15", "Session 18"). Here every
active cloth–body pair whose gradient presses it closer gets a stiffness c u uᵀ along its
distance gradient u (over the pair's cloth DOFs), with c = (∇E · u) / (f d |u|²) − uᵀHu / |u|⁴
(H's diagonal part): in the one-dimensional Newton model along u the direction then closes at
most the fraction f of the gap d, about what CCD would allow for that pair, so the pair stops
limiting everyone else's step; where H already holds the pair nothing is added.

Only the direction changes, not the energy, its gradient or the line search: the matrix stays
symmetric positive definite, the direction is one of descent, and the solver stops only on a
direction of the unmodified matrix (a pair in balance, ∇E · u ≈ 0, gets no stiffness anyway).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def contact_stiffness(scene, X, gradient, n_cloth: int, fraction: float, diagonal=None, dof_map=None):
    """The extra Newton-matrix term over all DOFs (scipy COO, [3 (N + Nb)]²), or None.

    Args:
        scene: the ContactScene whose active barrier set (``collisions_at(X)``) is used;
            pairs of cloth only (self-contact) or of body only are left out.
        X: [N + Nb, 3] the iterate; gradient: [3 (N + Nb)] ∇E at X (all terms).
        n_cloth: N (rows below it are cloth); fraction: f in (0, 1].
        diagonal, dof_map: the Newton matrix's diagonal over the reduced DOFs and the map of a
            DOF to its row (Assembler.dof_map): only the stiffness that the matrix's diagonal
            along u lacks is added (none where the barrier's own curvature already stops the
            pair, as at resting contacts near the solution).
    """
    coll = scene.collisions_at(X)
    E, F = scene.mesh.edges, scene.mesh.faces
    axes = np.arange(3)
    rows, cols, vals = [], [], []
    for group in (coll.vv_collisions, coll.ev_collisions, coll.ee_collisions, coll.fv_collisions):
        for c in group:
            ids = np.asarray(c.vertex_ids(E, F))
            ids = ids[ids >= 0]
            cloth = ids < n_cloth
            if cloth.all() or not cloth.any():
                continue
            pos = X[ids].ravel()
            d2 = c.compute_distance(pos)
            if not d2 > 0.0:
                continue
            dofs = (3 * ids[cloth][:, None] + axes).ravel()
            u = (np.asarray(c.compute_distance_gradient(pos)).reshape(-1, 3)[cloth]).ravel() / (2.0 * np.sqrt(d2))
            uu = float(u @ u)
            press = float(gradient[dofs] @ u)  # > 0: the energy falls as the gap closes
            if press <= 0.0 or uu <= 0.0:
                continue
            coef = press / (fraction * np.sqrt(d2) * uu)
            if diagonal is not None:  # the 1-D model along u already has uᵀHu / |u|⁴ (diagonal part)
                r = dof_map[dofs]
                coef -= float(np.sum(u[r >= 0] ** 2 * diagonal[r[r >= 0]])) / (uu * uu)
                if coef <= 0.0:
                    continue
            k = len(dofs)
            rows.append(np.repeat(dofs, k))
            cols.append(np.tile(dofs, k))
            vals.append(coef * np.outer(u, u).ravel())
    if not rows:
        return None
    N = X.size
    return sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(N, N))


def add_in_pattern(assembler, H, M):
    """H + M (M over all DOFs) in H's pattern when M's entries are in it (the preconditioner's
    fast path keeps working), else with scipy."""
    slot, values = assembler._sparse_slots(M)
    if slot is None:
        return H + assembler.reduce_matrix(M)
    out = H.copy()
    np.add.at(out.data, slot, values)
    return out
