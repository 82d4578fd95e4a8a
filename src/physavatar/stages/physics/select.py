"""Which estimator and which simulation model: :func:`fit_material` (the one entry point of both
estimators) and :func:`fit_selecting_integrator` (fits in implicit Euler, BDF2 and their blend,
keeps the lowest objective)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

from ...errors import PhysavatarError
from ...sim import Material, SimSettings
from .data import PhysicsData
from .fit_exact import fit_exact
from .fit_fd import fit_fd
from .objective import objective_value
from .outputs import FitResult
from .parameters import (
    EXACT_ITERATIONS,
    PAPER_ITERATIONS,
    SHAPE_WEIGHT,
    far_material,
    fit_settings,
)

# Where the fit of the BDF2 blend γ may start (fit_selecting_integrator): the one of these with
# the lowest objective at the implicit-Euler stiffnesses. Under contact the objective is rough at
# the 0.05 scale in γ, so LM from one fixed start can stop where it began (docs/physics.md).
BLEND_STARTS = (0.25, 0.5, 0.75, 1.0)
# The fits fit_selecting_integrator makes, in this order: implicit Euler; BDF2 (γ = 1) from its
# estimate; the blend with γ fitted. BDF2 itself stays a candidate because LM on γ can stop short
# of γ = 1 on a rough objective (docs/physics.md).
MODELS = ("euler", "bdf2", "bdf2_blend")


def fit_selecting_integrator(data: PhysicsData, initial: Material, settings: SimSettings | None = None,
                             iterations: int = EXACT_ITERATIONS, fit_density: bool = False, substeps: int = 1,
                             callback: Callable | None = None, shape_weight: float = SHAPE_WEIGHT) -> FitResult:
    """Fit in implicit Euler, in BDF2, and in their blend with γ fitted; keep the lowest objective.

    The fitted material is the best one *for the simulation model it was fitted in* (time
    integrator and step): under model error the models prefer different materials. Implicit
    Euler at one step per frame (the paper's) damps the motion numerically; a ground truth from
    a less damped simulator (or real cloth) is fitted much better by BDF2 at the same cost per
    step. The best model often lies between those two (docs/physics.md, "Which simulation
    model"), so a third fit makes the choice continuous: (κs, κb, γ) in the blend of the two
    (Material.bdf2_blend; γ = 0 is implicit Euler, 1 BDF2), from the implicit-Euler estimate and
    the γ of :data:`BLEND_STARTS` with the lowest objective there (4 plain simulations). The fits
    run in the order of :data:`MODELS`, the BDF2 ones from the implicit-Euler estimate. The
    result is the chosen fit; its material records the integrator and γ (which
    :func:`physavatar.sim.simulate` then uses), ``model_selection`` every fit and the scan;
    simulations and wall time count all.
    """
    settings = settings or fit_settings()
    fits = {}
    t0 = time.perf_counter()
    history = []  # every fit's rows, numbered, timed and counted on from the first fit's
    scan = {}
    for key in MODELS:
        integrator = "euler" if key == "euler" else "bdf2"
        if key == "euler":
            start = initial
        elif key == "bdf2":  # BDF2 itself (γ = 1), from the implicit-Euler estimate
            start = dataclasses.replace(fits["euler"].material, name=initial.name, integrator="bdf2", bdf2_blend=1.0)
        else:  # γ fitted; its start from a coarse scan at the implicit-Euler estimate (plain simulations)
            candidates = [dataclasses.replace(fits["euler"].material, name=initial.name, integrator="bdf2",
                                              bdf2_blend=g) for g in BLEND_STARTS]
            bdf2 = dataclasses.replace(settings, integrator="bdf2")
            scan = {"bdf2_blend": list(BLEND_STARTS),
                    "objective": [objective_value(data, m, bdf2, substeps, shape_weight) for m in candidates]}
            start = candidates[int(np.argmin(scan["objective"]))]

        def tagged(row, key=key, offset=len(history), t_before=time.perf_counter() - t0,
                   sims_before=sum(r.simulations for r in fits.values()) + len(scan.get("objective", ()))):
            row = dict(row, iteration=row["iteration"] + offset, integrator=key,
                       wall_time_s=row["wall_time_s"] + t_before, simulations=row["simulations"] + sims_before)
            history.append(row)
            if callback is not None:
                callback(row)

        fits[key] = fit_exact(data, start, dataclasses.replace(settings, integrator=integrator), iterations,
                              fit_density, substeps, callback=tagged, shape_weight=shape_weight,
                              fit_blend=key == "bdf2_blend")
    chosen = min(fits, key=lambda k: fits[k].objective)
    best = fits[chosen]
    best.model_selection = {
        "chosen": chosen,
        "criterion": "lower objective on the fitted window (docs/physics.md, 'Which simulation model')",
        "bdf2_blend_start_scan": scan,
        "fits": {k: {"objective": r.objective, "loss": r.loss, "rms_mm": r.rms_mm, "iterations": r.iterations,
                     "simulations": r.simulations, "wall_time_s": r.wall_time,
                     "stretch_ratio": r.material.stretch_ratio, "bend_ratio": r.material.bend_ratio,
                     "bdf2_blend": r.material.bdf2_blend if k != "euler" else None,
                     "material": r.material.to_dict()} for k, r in fits.items()},
    }
    if best.material.integrator == "bdf2" and best.material.bdf2_blend == 0.0:
        # γ = 0 is implicit Euler exactly (ClothSim.step_base): the material says so, not "bdf2"
        best.material = dataclasses.replace(best.material, integrator="euler", bdf2_blend=1.0)
        best.model_selection["recorded_as"] = "euler: the blend ended at γ = 0, which is implicit Euler"
    best.history = history
    best.iterations = len(history) - len(fits)
    best.simulations = sum(r.simulations for r in fits.values()) + len(scan["objective"])
    best.wall_time = time.perf_counter() - t0
    best.initial = initial
    return best


def fit_material(data: PhysicsData, initial: Material | None = None, gradient: str = "exact",
                 iterations: int | None = None, fit_density: bool = False, settings: SimSettings | None = None,
                 workers: int = 2, substeps: int = 1, callback: Callable | None = None,
                 shape_weight: float | None = None, select_integrator: bool = False) -> FitResult:
    """Estimate the garment material from ``data`` (one entry point for both estimators).

    initial: start material (default :func:`far_material`); its density is the prior that
    stays fixed unless ``fit_density``. gradient: "fd" (the paper) or "exact".
    iterations: default 100 (fd, the paper) or 15 (exact). shape_weight: :func:`fit_residuals`
    (default :data:`SHAPE_WEIGHT` with exact, 0 — the paper's L_sim — with fd).
    select_integrator (exact only): fit in implicit Euler and BDF2 and keep the better model
    (:func:`fit_selecting_integrator`); otherwise ``settings.integrator``.
    """
    initial = initial or far_material()
    if shape_weight is None:
        shape_weight = SHAPE_WEIGHT if gradient == "exact" else 0.0
    if gradient == "fd":
        return fit_fd(data, initial, settings, iterations or PAPER_ITERATIONS, fit_density, workers, substeps, callback,
                      shape_weight=shape_weight)
    if gradient == "exact":
        fit = fit_selecting_integrator if select_integrator else fit_exact
        return fit(data, initial, settings, iterations or EXACT_ITERATIONS, fit_density, substeps, callback=callback,
                   shape_weight=shape_weight)
    raise PhysavatarError(None, f"gradient must be 'fd' or 'exact', got {gradient!r}")
