"""Cloth simulator: implicit Euler in the C-IPC formulation on top of the IPC Toolkit.

The term protocol (terms.py: energy, gradient, one Hessian type, ``begin_step(state)``, the
declared ``parameter``); energies (energies.py): inertia, gravity, StVK / Neo-Hookean membrane,
discrete-shell bending, Rayleigh damping; contact (contact.py): ipctk barrier, lagged friction,
CCD; assembly and linear solves (assembly.py); the Newton step (solver.py, settings.py, where it
starts: start.py); a whole sequence (simulate.py); forward sensitivities of a simulation with
respect to the terms' parameters (sensitivity.py). Units and defaults: docs/simulation.md.
"""

import ipctk as _ipctk

# ipctk logs a warning for every additive-CCD query with a near-zero gap; on a 24-frame material
# fit that is thousands of console lines. The solver checks what matters itself (every step is
# intersection-free and finite; the tests run ipctk's intersection check), so only errors show.
_ipctk.set_logger_level(_ipctk.LoggerLevel.error)

from .assembly import Linearization  # noqa: E402
from .material import PRESETS, Material, preset  # noqa: E402
from .settings import SimSettings, StepStats  # noqa: E402
from .simulate import simulate  # noqa: E402
from .solver import ClothSim  # noqa: E402

__all__ = [
    "ClothSim",
    "Linearization",
    "Material",
    "PRESETS",
    "SimSettings",
    "StepStats",
    "preset",
    "simulate",
]
