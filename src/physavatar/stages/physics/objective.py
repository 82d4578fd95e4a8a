"""The simulation of a window and what the estimators minimise.

:func:`rollout` simulates the fitted window (with forward sensitivities when asked,
:mod:`physavatar.sim.sensitivity`); :func:`fit_residuals` is the residual vector both estimators
minimise: Eq. 6's x_t − x̂_t and, with a shape weight, the local shape w·L(x_t − x̂_t)
(:func:`shape_operator`). :func:`ratio_intervals` turns the residuals' Jacobian into confidence
intervals of the identifiable ratios κs/ρ and κb/ρ.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import scipy.sparse as sp

from ...sim import Material, SimSettings
from ...sim.sensitivity import BLEND, Rollout
from ...sim.sensitivity import rollout as sim_rollout
from .data import PhysicsData


def rollout(data: PhysicsData, material: Material, settings: SimSettings | None = None,
            parameters=None, substeps: int = 1) -> Rollout:
    """Simulate ``data``'s window with ``material`` from ``data.initial`` (default the reference
    frame 0) at rest (:func:`physavatar.sim.sensitivity.rollout`). Returns a :class:`Rollout`.

    Args:
        parameters: names (from :data:`~.parameters.PARAMETERS` and the blend γ,
            :data:`~physavatar.sim.sensitivity.BLEND`) to differentiate with respect to (in log
            space; γ as is), or None for a plain simulation.
        substeps: implicit steps per frame (body and boundary interpolated linearly).
    """
    x0 = data.reference[0] if data.initial is None else data.initial
    return sim_rollout(data.rest, data.faces, material, data.collider, data.collider_faces, data.boundary,
                       data.boundary_targets, data.fps, substeps, settings, x0, parameters)


# -- loss ----------------------------------------------------------------------------------------


def trajectory_loss(positions: np.ndarray, reference: np.ndarray) -> float:
    """L_sim (Eq. 6): Σ_{t≥1} Σ_i ‖x_t,i − x̂_t,i‖² [m²] (frame 0 is the shared initial state)."""
    d = np.asarray(positions)[1:] - np.asarray(reference)[1:]
    return float(np.sum(d * d))


def rms_mm(loss: float, data: PhysicsData) -> float:
    """The loss as an RMS vertex distance [mm] over the fitted frames."""
    return 1e3 * math.sqrt(loss / ((data.frames - 1) * data.reference.shape[1]))


def shape_operator(faces: np.ndarray, n: int) -> sp.csr_matrix:
    """[n, n] uniform graph Laplacian I − D⁻¹A of the garment mesh: (L x)_i = x_i − mean of its
    neighbours, the umbrella operator (a discrete mean-curvature normal, unscaled)."""
    f = np.asarray(faces, dtype=np.int64)
    e = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    deg = np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1.0)
    return (sp.eye(n, format="csr") - sp.diags(1.0 / deg) @ A).tocsr()


def fit_residuals(positions: np.ndarray, data: PhysicsData, shape_weight: float = 0.0,
                  jacobian: np.ndarray | None = None):
    """The residual vector the estimators minimise, and its Jacobian.

    r = x_t − x̂_t over frames ≥ 1 (Eq. 6), and with ``shape_weight`` w > 0 also w·L(x_t − x̂_t)
    (:func:`shape_operator`): the difference of local shape, blind to a smooth drift of the
    whole garment. Model error (another simulator's time stepping and damping, docs/physics.md)
    mostly shows as such a drift, in which κb is nearly invisible ("Local shape" there);
    bending shows in the local shape.
    positions: [T, N, 3]; jacobian: [T, N, 3, P] or None. Returns (r [M], J [M, P] or None).
    """
    d = (np.asarray(positions) - data.reference)[1:]
    res = [d.reshape(-1)]
    jac = None if jacobian is None else [jacobian[1:].reshape(-1, jacobian.shape[-1])]
    if shape_weight > 0:
        L = shape_operator(data.faces, d.shape[1])
        res.append(shape_weight * np.stack([L @ f for f in d]).reshape(-1))
        if jacobian is not None:
            P = jacobian.shape[-1]
            Jl = np.stack([(L @ f.reshape(f.shape[0], -1)).reshape(f.shape) for f in jacobian[1:]])
            jac.append(shape_weight * Jl.reshape(-1, P))
    r = np.concatenate(res)
    return r, (None if jac is None else np.concatenate(jac))


def objective_value(data: PhysicsData, material: Material, settings: SimSettings | None = None, substeps: int = 1,
               shape_weight: float = 0.0) -> float:
    """The estimators' objective ‖r‖² (:func:`fit_residuals`) of one plain simulation (inf if it fails)."""
    try:
        r = rollout(data, material, settings, substeps=substeps)
    except (FloatingPointError, np.linalg.LinAlgError, RuntimeError):
        return math.inf
    res, _ = fit_residuals(r.positions, data, shape_weight)
    return float(res @ res)


def simulation_loss(data: PhysicsData, material: Material, settings: SimSettings | None = None,
                    substeps: int = 1) -> float:
    """L_sim of ``material`` on ``data`` (inf when the simulation fails)."""
    return objective_value(data, material, settings, substeps)



def ratio_intervals(jacobian: np.ndarray, residual: np.ndarray, names, material: Material, z: float = 1.96):
    """95% intervals of κs/ρ and κb/ρ from the Gauss–Newton curvature.

    Args:
        jacobian: [M, P] ∂r/∂log θ (columns in ``names``); residual: [M].

    Only the ratios matter, and ∂r/∂log κ at fixed ρ is ∂r/∂log(κ/ρ), so the stiffness columns
    are the Jacobian of the ratios. σ² = ‖r‖²/(M − P), Cov = σ² (JᵀJ)⁻¹ in log space, over the
    stiffness columns and the blend γ's when it was fitted (the ratios' intervals then include
    what γ's uncertainty does to them); ρ's column is left out (only the ratios are identifiable).
    Returns (intervals {name: [lo, hi]}, log std {name: σ}; γ's std as "bdf2_blend").
    """
    cols = [names.index(n) for n in ("stretch_stiffness", "bend_stiffness") if n in names]
    keys = {"stretch_stiffness": "stretch_ratio", "bend_stiffness": "bend_ratio"}
    if not cols or jacobian is None:
        return {}, {}
    extra = [names.index(BLEND)] if BLEND in names else []
    J = jacobian[:, cols + extra]
    M = len(residual)
    sigma2 = float(residual @ residual) / max(M - J.shape[1], 1)
    JtJ = J.T @ J
    try:
        cov = sigma2 * np.linalg.inv(JtJ)
    except np.linalg.LinAlgError:
        cov = np.full((J.shape[1], J.shape[1]), np.inf)
    intervals, stds = {}, {}
    if extra:  # γ is fitted as is: its std is absolute
        stds[BLEND] = float(math.sqrt(max(cov[-1, -1], 0.0))) if np.isfinite(cov[-1, -1]) else math.inf
    for i, c in enumerate(cols):
        name = names[c]
        std = float(math.sqrt(max(cov[i, i], 0.0))) if np.isfinite(cov[i, i]) else math.inf
        value = getattr(material, name) / material.density
        key = keys[name]
        stds[key] = std
        # an unconstrained ratio (flat loss along it) has no finite interval
        intervals[key] = [value * math.exp(-z * std), value * math.exp(z * std)] if z * std < 50 else None
    return intervals, stds


# -- the fits' records ----------------------------------------------------------------------------


def history_row(it, loss, data, names, theta, t_start, sims, objective=None) -> dict:
    """One row of a fit's history (fit_log.csv): iteration, L_sim and its RMS distance, the
    objective, the parameters (from θ), wall time and simulations so far."""
    row = {"iteration": it, "loss": float(loss), "rms_mm": rms_mm(loss, data),
           "objective": float(loss if objective is None else objective)}
    for n, v in zip(names, theta):
        row[n] = float(v if n == BLEND else math.exp(v))
    row["wall_time_s"] = time.perf_counter() - t_start
    row["simulations"] = sims
    return row


def settings_record(settings, substeps, fps) -> dict:
    """The simulator settings of a fit as material.json records them (with substeps and dt)."""
    d = dataclasses.asdict(settings)
    d["substeps"] = substeps
    d["dt"] = 1.0 / (fps * substeps)  # the step the simulations took (rollout sets it from the data's fps)
    d["gravity"] = list(d["gravity"])
    return d

