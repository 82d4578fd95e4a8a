"""Levenberg–Marquardt: one box-constrained step of the damped Gauss–Newton model."""

from __future__ import annotations

import numpy as np


def lm_step(J: np.ndarray, res: np.ndarray, theta: np.ndarray, lo: np.ndarray, hi: np.ndarray, lam: float,
            radius: float) -> tuple[np.ndarray, float]:
    """One Levenberg–Marquardt step for residuals ``res`` [M] with Jacobian ``J`` [M, P] at ``theta`` [P].

    Minimises the damped linear model ‖r + Jδ‖² + λ δᵀ diag(JᵀJ) δ over the box |δ_p| ≤ ``radius``
    ∩ [``lo``, ``hi``] (in log space no parameter then moves more than a factor e^radius per
    step: the residual model is only locally linear). The box problem is solved as such (bounded
    least squares on the P×P Cholesky factor of JᵀJ + λD), not by scaling or clipping the
    unconstrained step: scaling shrinks the well-determined parameters with a long, poorly
    determined one, and clipping at a bound turns the free parameters' direction. A parameter
    pinned on a bound with no room stays. Returns (trial θ, predicted decrease ‖r‖² − ‖r + Jδ‖²).
    """
    from scipy.optimize import lsq_linear

    g = J.T @ res
    JtJ = J.T @ J
    d = np.maximum(np.diag(JtJ), 1e-12 * max(np.max(np.diag(JtJ)), 1e-300))
    A = JtJ + lam * np.diag(d)
    R = np.linalg.cholesky(A).T  # RᵀR = A: ‖Rδ + R⁻ᵀg‖² = δᵀAδ + 2gᵀδ + const
    rhs = -np.linalg.solve(R.T, g)
    lower = np.maximum(lo - theta, -radius)
    upper = np.minimum(hi - theta, radius)
    lower, upper = np.minimum(lower, 0.0), np.maximum(upper, 0.0)
    fixed = upper - lower < 1e-12  # a parameter pinned on a bound with no room (lsq_linear needs lb < ub)
    delta = np.zeros_like(theta)
    if (~fixed).any():
        Rf = R[:, ~fixed]
        delta[~fixed] = lsq_linear(Rf, rhs, bounds=(lower[~fixed], upper[~fixed]), method="bvls").x
    delta = np.clip(theta + delta, lo, hi) - theta
    predicted = -(2.0 * g @ delta + delta @ JtJ @ delta)  # ‖r‖² − ‖r + Jδ‖²
    return theta + delta, float(predicted)
