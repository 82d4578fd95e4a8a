"""Material estimation with exact gradients: forward sensitivities through the implicit steps
(:mod:`physavatar.sim.sensitivity`) and Levenberg–Marquardt (:func:`physavatar.optim.lm_step`) on
the trajectory residuals (:func:`~.objective.fit_residuals`)."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import numpy as np

from ...optim import lm_step
from ...sim import Material, SimSettings
from ...sim.sensitivity import BLEND
from .data import PhysicsData
from .objective import (
    fit_residuals,
    history_row,
    ratio_intervals,
    rms_mm,
    rollout,
    settings_record,
    trajectory_loss,
)
from .outputs import FitResult
from .parameters import (
    EXACT_ITERATIONS,
    PARAMETERS,
    fit_settings,
    log_theta,
    theta_bounds,
    with_log_params,
)


def fit_exact(data: PhysicsData, initial: Material, settings: SimSettings | None = None,
              iterations: int = EXACT_ITERATIONS, fit_density: bool = False, substeps: int = 1,
              tolerance: float = 1e-4, callback: Callable | None = None, max_rejections: int = 4,
              radius: float = 1.0, shape_weight: float = 0.0, fit_blend: bool = False) -> FitResult:
    """Levenberg–Marquardt on the trajectory residuals with exact Jacobians (:func:`rollout`).

    Each iteration simulates once with sensitivities (J [M, P], P = 2 or 3), solves
    (JᵀJ + λ diag JᵀJ) δ = −Jᵀr within a box around θ and the bounds (:func:`lm_step`), and
    tries θ + δ (a second simulation, which also provides the next Jacobian when accepted).
    A box trust region in log space (max norm, ``radius`` to start) follows the gain ratio ϱ of the
    actual to the predicted loss decrease (Nielsen / Moré): ϱ > 0.75 doubles it (up to 2), ϱ <
    0.25 halves it, a rejected step halves the region below the step tried; λ follows the same
    way (×⅓ / ×4). L_sim has kinks at the 1 % parameter scale (contact events), so a rejected
    step shrinks the region instead of only growing λ. With ``fit_density`` the scaling
    direction is flat (JᵀJ singular there); the damping keeps the step finite and ρ stays near
    its start. Stops when an accepted step improves the loss by less than ``tolerance``
    (relative), after ``max_rejections`` rejected steps in a row, when the region falls
    below 1e-3 (a 0.1 % change), or after ``iterations`` steps.

    ``shape_weight`` w > 0 adds the local-shape residuals w·L(x_t − x̂_t) to the objective
    (:func:`fit_residuals`); the reported ``loss`` stays L_sim (Eq. 6), ``objective`` is what
    was minimised (and the intervals are its curvature's).

    ``fit_blend`` (BDF2 only) fits the blend γ (Material.bdf2_blend, from the initial material's)
    with the stiffnesses: how much numerical damping the model has, from the data.
    """
    settings = settings or fit_settings()
    names = PARAMETERS if fit_density else PARAMETERS[1:]
    if fit_blend:
        if settings.integrator != "bdf2":
            raise ValueError("fit_blend: the blend γ is a parameter of BDF2 (settings.integrator='bdf2')")
        names = names + (BLEND,)
    lo, hi = theta_bounds(names)
    theta = np.clip(log_theta(initial, names), lo, hi)
    t_start = time.perf_counter()
    sims = 0
    history = []

    def evaluate(th):
        m = with_log_params(initial, names, th)
        r = rollout(data, m, settings, parameters=names, substeps=substeps)
        res, J = fit_residuals(r.positions, data, shape_weight, r.jacobian)
        return float(res @ res), res, J, trajectory_loss(r.positions, data.reference)

    loss, res, J, lsim = evaluate(theta)
    sims += 1
    lam = 1e-3
    rejected = 0
    row = history_row(0, lsim, data, names, theta, t_start, sims, loss)
    history.append(row)
    if callback is not None:
        callback(row)
    for it in range(1, iterations + 1):
        trial, predicted = lm_step(J, res, theta, lo, hi, lam, radius)
        tried = float(np.max(np.abs(trial - theta)))
        if tried < 1e-12 or predicted <= 0:
            break  # every free parameter is held on a bound: a constrained stationary point
        try:
            new_loss, new_res, new_J, new_lsim = evaluate(trial)
        except (FloatingPointError, np.linalg.LinAlgError, RuntimeError):
            new_loss = math.inf
        sims += 1
        gain = (loss - new_loss) / predicted
        improved = new_loss < loss
        rel = (loss - new_loss) / max(loss, 1e-300)
        if improved:
            theta, loss, res, J, lsim = trial, new_loss, new_res, new_J, new_lsim
            if gain > 0.75:
                radius = min(2.0 * radius, 2.0)
                lam = max(lam / 3.0, 1e-9)
            elif gain < 0.25:
                radius = 0.5 * max(tried, 1e-3)
                lam *= 4.0
        else:
            radius = 0.5 * tried
            lam *= 4.0
        row = history_row(it, lsim, data, names, theta, t_start, sims, loss)
        row["accepted"] = bool(improved)
        history.append(row)
        if callback is not None:
            callback(row)
        rejected = 0 if improved else rejected + 1
        if improved and rel < tolerance:
            break
        if rejected >= max_rejections or radius < 1e-3:
            break  # no better point within a shrinking region: at a (local) minimum
    material = dataclasses.replace(with_log_params(initial, names, theta), name="fitted (exact)",
                                   integrator=settings.integrator)
    intervals, stds = ratio_intervals(J, res, list(names), material)
    return FitResult(material, initial, float(lsim), rms_mm(lsim, data), len(history) - 1, sims,
                     time.perf_counter() - t_start, "exact", names, history, intervals, stds, data.frames,
                     settings_record(settings, substeps, data.fps), shape_weight=shape_weight, objective=float(loss))
