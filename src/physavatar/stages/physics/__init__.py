"""Garment material estimation (PhysAvatar Sec. 3.2, App. A.3, Algorithm 1).

Given a tracked garment [T, N, 3], its boundary (Dirichlet) vertices and the body collider per
frame, find the cloth material whose simulation best reproduces the tracked motion:

    L_sim(θ) = Σ_{t=1}^{T-1} ‖x_t(θ) − x̂_t‖²         (Eq. 6; x_0 = x̂_0, v_0 = 0)

where x_{t+1} = f(x_t, v_t, boundary_{t+1}, body_{t+1}; θ) is one implicit step of
:mod:`physavatar.sim` (Eq. 5). θ = log(ρ, κs, κb): only κs/ρ and κb/ρ change the motion
(DESIGN.md "Conventions"), so by default ρ is held at a prior and (κs, κb) are fitted.

Two estimators:

- ``gradient="fd"`` — the paper's: forward finite differences of L_sim per parameter (Eq. 7),
  Adam, 100 iterations; the 1 + P simulations of an iteration run in a process pool.
- ``gradient="exact"`` — forward sensitivities S_t = ∂x_t/∂θ through the implicit steps (each
  step's solution satisfies ∇E(x_{t+1}) = 0, so H S_{t+1} = −∂(∇E)/∂θ − ∂(∇E)/∂x_t S_t −
  ∂(∇E)/∂v_t V_t with H the exact Hessian at the solution), and Levenberg–Marquardt on the
  residuals r = x_t − x̂_t with their Jacobian J = S. The Gauss–Newton curvature JᵀJ also gives
  the confidence intervals of the identifiable ratios. By default the residuals also include the
  local shape w·L r (:func:`~.objective.fit_residuals`, :data:`~.parameters.SHAPE_WEIGHT`), where
  bending shows when the ground truth comes from another simulator.

The stage is :func:`run` (``run(source, out=, config=PhysicsConfig(...))``); its modules:

- :mod:`.config`      :class:`~.config.PhysicsConfig` (the ``fit-physics`` options), the settings
                      of ``physavatar run``;
- :mod:`.parameters`  what is fitted: parameters, bounds, the paper's step sizes in our units,
                      the fitting simulator settings, the far initial material;
- :mod:`.data`        :class:`~.data.PhysicsData` (what is fitted to) read from a tracked folder,
                      a capture or a garment sequence; the start state (:func:`~.data.clear_start`);
- :mod:`.proxy`       a coarse simulation proxy of a big garment, and the data moved onto it;
- :mod:`.objective`   the window's simulation (:func:`~.objective.rollout`), residuals, loss,
                      confidence intervals;
- :mod:`.fit_fd`      the paper's estimator (finite differences + Adam, in a process pool);
- :mod:`.fit_exact`   forward sensitivities + Levenberg–Marquardt;
- :mod:`.select`      :func:`~.select.fit_material` (either estimator) and the integrator selection;
- :mod:`.outputs`     :class:`~.outputs.FitResult`, material.json, fit_log.csv, fit.png;
- :mod:`.stage`       :func:`run`.

Units and the mapping of the paper's step sizes and ranges: docs/physics.md.
"""

from .config import PhysicsConfig, pipeline_config
from .outputs import FitResult
from .stage import run

__all__ = ["FitResult", "PhysicsConfig", "pipeline_config", "run"]
