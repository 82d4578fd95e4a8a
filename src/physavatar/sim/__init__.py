"""Cloth simulator: implicit Euler in the C-IPC formulation on top of the IPC Toolkit.

Energies (energies.py): inertia, gravity, StVK / Neo-Hookean membrane, discrete-shell bending,
Rayleigh damping; contact (contact.py): ipctk barrier, lagged friction, CCD; Newton solver and
the public API (solver.py). Units and defaults: docs/simulation.md.
"""

from .material import PRESETS, Material, preset
from .solver import ClothSim, Linearization, SimSettings, StepStats, simulate

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
