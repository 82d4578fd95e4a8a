"""What material estimation fits, in which units and ranges, with which step sizes.

θ = log(ρ, κs, κb) (the BDF2 blend γ, when fitted, as is in [0, 1]); only κs/ρ and κb/ρ change
the motion, so by default ρ is held at a prior. The paper's hyper-parameters (App. A.3.3 and the
official Codim-IPC driver) are mapped to our units and log-parameters here; docs/physics.md
gives the mapping and the measurements behind the defaults.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ...sim import Material, SimSettings, preset
from ...sim.material import CODIM_BASE_POISSON, CODIM_BASE_THICKNESS, CODIM_BASE_YOUNG
from ...sim.sensitivity import BLEND

PARAMETERS = ("density", "stretch_stiffness", "bend_stiffness")
# The BDF2 blend γ (BLEND, Material.bdf2_blend) is a parameter of the simulation model, fitted with
# the stiffnesses in BDF2 (fit_exact(fit_blend=True)); unlike them it is optimised as is, in [0, 1].
SYMBOLS = {"density": "rho", "stretch_stiffness": "ks", "bend_stiffness": "kb", BLEND: "gamma"}

# -- the paper's hyper-parameters (App. A.3.3 and the official Codim-IPC driver), in our units --
#
# The paper optimises density [kg/m³] and two multipliers of a base fabric (docs/simulation.md):
# FD steps δρ = 5 kg/m³, δκs = δκb = 0.05 (multipliers), from ρ = 320 kg/m³ and multipliers 1;
# the official driver uses Adam with lr 0.1 (cosine-annealed to 0.04 over the iterations) on the
# raw values. We optimise log-parameters, so each step is mapped at the paper's initial point:
# a multiplier step of 0.05 at 1 is Δlog κ = 0.05, lr 0.1 is 0.1 per iteration; for the density
# δ = log(1 + 5/320) and lr = 0.1/320 (density hardly moves in the paper's optimiser either).
FD_STEP = {"density": math.log1p(5.0 / 320.0), "stretch_stiffness": 0.05, "bend_stiffness": 0.05}
ADAM_LR = {"density": 0.1 / 320.0, "stretch_stiffness": 0.1, "bend_stiffness": 0.1}
ADAM_LR_FINAL_FRACTION = 0.4  # cosine annealing 0.1 -> 0.04
PAPER_ITERATIONS = 100
EXACT_ITERATIONS = 15  # the exact estimator's default (Levenberg–Marquardt converges in far fewer)
PAPER_WINDOW = 24  # frames (App. A.3.1)
# Newton tolerance of the fitting simulations [m/s]: at the simulator's default (1e-3) the solver
# error alone lifts L_sim above the noise floor at the true material and makes it rough at the
# 1 % parameter scale; 1e-5 puts it at the floor (docs/physics.md).
FIT_NEWTON_TOL = 1e-5
# Weight w of the local-shape residuals w·L(x − x̂) next to Eq. 6's x − x̂ (fit_residuals) in the
# exact estimator's objective. Under model error Eq. 6 alone is nearly flat in κb; the shape
# residuals have their minimum near the true κb. w = 3: docs/physics.md ("Local shape"); 0 is
# the paper's L_sim.
SHAPE_WEIGHT = 3.0
# the weights fit-physics chooses between by the frames after the window (--select-shape-weight;
# docs/physics.md "Issue 22, session 36"): with the shape term, and the paper's L_sim alone
SHAPE_WEIGHTS = (SHAPE_WEIGHT, 0.0)


def fit_settings(**changes) -> SimSettings:
    """The simulator settings material estimation uses by default (SimSettings + FIT_NEWTON_TOL).

    The fits keep the ∞-norm stopping rule (newton_norm="max") that FIT_NEWTON_TOL was chosen
    with; forward simulations default to Codim-IPC's looser RMS rule (docs/simulation.md).
    """
    return dataclasses.replace(SimSettings(newton_tol=FIT_NEWTON_TOL, newton_norm="max"), **changes)


# The paper's ranges (ρ ∈ [200, 640] kg/m³, multipliers ∈ [0.1, 8]) mapped to SI are
# ρ ∈ [0.066, 0.21] kg/m², κs ∈ [2.5, 199] N/m, κb ∈ [2.3e-8, 1.8e-6] N·m. The measured fabrics
# (sim PRESETS, Wang et al. 2011) lie partly outside them (denim ρ 0.32, κs 547; every κb is
# 10–100× the base), so the bounds are widened to cover both, in log space.
PAPER_RANGES = {
    "density": (200.0 * CODIM_BASE_THICKNESS, 640.0 * CODIM_BASE_THICKNESS),
    "stretch_stiffness": (0.1 * CODIM_BASE_YOUNG * CODIM_BASE_THICKNESS, 8.0 * CODIM_BASE_YOUNG * CODIM_BASE_THICKNESS),
    "bend_stiffness": tuple(
        m * CODIM_BASE_YOUNG * CODIM_BASE_THICKNESS**3 / (12.0 * (1.0 - CODIM_BASE_POISSON**2)) for m in (0.1, 8.0)
    ),
}
BOUNDS = {
    "density": (0.02, 1.0),  # kg/m²
    "stretch_stiffness": (1.0, 5000.0),  # N/m
    "bend_stiffness": (1e-8, 1e-3),  # N·m
}


def far_material(density: float | None = None) -> Material:
    """The standard far initial guess: the official driver's start (Codim-IPC base fabric,
    multipliers 1), with the density prior (default: the medium fabric's)."""
    base = Material()
    return dataclasses.replace(base, density=density or preset("cotton").density, name="far (codim-ipc base)")


def with_log_params(material: Material, names, log_values) -> Material:
    """``material`` with the parameters ``names`` set from θ (log values; the blend γ as is)."""
    return dataclasses.replace(material, **{n: float(min(max(v, 0.0), 1.0) if n == BLEND else math.exp(v))
                                            for n, v in zip(names, log_values)})


def log_theta(material: Material, names) -> np.ndarray:
    """θ of ``material`` for the parameters ``names`` (log values; the blend γ as is)."""
    return np.array([getattr(material, n) if n == BLEND else math.log(getattr(material, n)) for n in names])


def theta_bounds(names):
    """Bounds of θ: log :data:`BOUNDS`, and [0, 1] for the blend γ."""
    lo = np.array([0.0 if n == BLEND else math.log(BOUNDS[n][0]) for n in names])
    hi = np.array([1.0 if n == BLEND else math.log(BOUNDS[n][1]) for n in names])
    return lo, hi
