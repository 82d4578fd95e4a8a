"""A fit's result (:class:`FitResult`) and the files it is written to: material.json
(:class:`~physavatar.data.material.FittedMaterial`), fit_log.csv and fit.png."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from ...data.material import FILE as MATERIAL
from ...data.material import FittedMaterial
from ...files import atomic_path, write_text_atomic
from ...sim import Material
from ...sim.sensitivity import BLEND
from .parameters import BOUNDS, PARAMETERS


@dataclasses.dataclass
class FitResult:
    """A fitted material and how it was found.

    history: one dict per iteration (iteration, loss, rms_mm, log parameters, wall time).
    ratio_intervals: 95% intervals of κs/ρ and κb/ρ from the Gauss–Newton curvature.
    """

    material: Material
    initial: Material
    loss: float
    rms_mm: float
    iterations: int
    simulations: int
    wall_time: float
    gradient: str
    fitted: tuple
    history: list
    ratio_intervals: dict
    log_std: dict
    window: int
    settings: dict
    proxy: dict | None = None  # the coarse proxy fitted on (.proxy), if any
    shape_weight: float = 0.0  # weight of the local-shape residuals (fit_residuals)
    objective: float | None = None  # what was minimised (= loss when shape_weight is 0)
    model_selection: dict | None = None  # fit_selecting_integrator: both fits and the choice
    start_state: dict | None = None  # clear_start: crossings and gap of the start frame, what was pushed
    shape_selection: dict | None = None  # stage.select_shape_weight: the fits with and without the shape term

    def at_bound(self) -> list:
        """Fitted parameters that ended on their search bound (:data:`BOUNDS`): the data pushed
        them out of the physical range — usually model error (e.g. a coarse proxy), not a fit."""
        return [n for n in self.fitted if n != BLEND  # γ = 0 or 1 is a model, not a failure
                and min(abs(math.log(getattr(self.material, n) / b)) for b in BOUNDS[n]) < 1e-6]

    def to_json(self) -> dict:
        m = self.material
        return {
            "material": m.to_dict(),
            "ratios": {
                "stretch_ratio": {"value": m.stretch_ratio, "unit": "m^2/s^2", "symbol": "ks/rho",
                                  "interval95": self.ratio_intervals.get("stretch_ratio")},
                "bend_ratio": {"value": m.bend_ratio, "unit": "m^3/s^2", "symbol": "kb/rho",
                               "interval95": self.ratio_intervals.get("bend_ratio")},
            },
            "log_std": self.log_std,
            "identifiable": "only ks/rho and kb/rho change the motion; rho is a prior unless fitted",
            "fitted_parameters": list(self.fitted),
            "initial": self.initial.to_dict(),
            "loss": self.loss,
            "loss_unit": "m^2 (sum over fitted frames and vertices of squared distance)",
            "objective": self.loss if self.objective is None else self.objective,
            "shape_weight": self.shape_weight,
            "rms_mm": self.rms_mm,
            "initial_rms_mm": self.history[0]["rms_mm"] if self.history else None,
            "at_bound": self.at_bound(),
            "iterations": self.iterations,
            "simulations": self.simulations,
            "wall_time_s": self.wall_time,
            "gradient": self.gradient,
            "window_frames": self.window,
            "settings": self.settings,
            "integrator": m.integrator,
            "model_selection": self.model_selection,
            "proxy": self.proxy,
            "start_state": self.start_state,
            **({"shape_selection": self.shape_selection} if self.shape_selection else {}),
        }


def write_outputs(out: str | Path, result: FitResult) -> None:
    """material.json, fit_log.csv and fit.png in ``out`` (atomic writes)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    FittedMaterial.from_json(result.to_json()).save(out / MATERIAL)
    params = logged_parameters(result)
    write_fit_log(out / "fit_log.csv", result, params)
    plot_fit(out / "fit.png", result, params)


def logged_parameters(result: FitResult) -> list[str]:
    """The parameters of the history's rows: with the integrator selection, the BDF2 fit's rows add γ."""
    return [n for n in PARAMETERS + (BLEND,) if n in result.fitted or any(n in r for r in result.history)]


def write_fit_log(path: Path, result: FitResult, params: list[str]) -> None:
    """fit_log.csv: one row per iteration (a parameter a row's fit did not have, γ in implicit
    Euler, is empty); with the integrator selection, the integrator of each row."""
    cols = ["iteration", "loss", "rms_mm"] + params + ["wall_time_s", "simulations"]
    if any("integrator" in row for row in result.history):
        cols.append("integrator")  # fit_selecting_integrator: implicit Euler's iterations, then BDF2's
    lines = [",".join(cols)]
    for row in result.history:
        lines.append(",".join("" if c not in row else f"{row[c]:.9g}" if isinstance(row[c], float) else str(row[c])
                              for c in cols))
    write_text_atomic(path, "\n".join(lines) + "\n")


def plot_fit(path: Path, result: FitResult, params: list[str]) -> None:
    """fit.png: the loss and each parameter per iteration (dashed lines where a further fit of
    the integrator selection begins)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    it = [r["iteration"] for r in result.history]
    fig, axes = plt.subplots(1, 1 + len(params), figsize=(4 * (1 + len(params)), 3.2))
    axes[0].semilogy(it, [r["loss"] for r in result.history])
    axes[0].set_xlabel("iteration")
    axes[0].set_ylabel("L_sim [m²]")
    axes[0].set_title(f"loss ({result.gradient})")
    sel = result.model_selection
    if sel:
        starts = [b["iteration"] for a, b in zip(result.history, result.history[1:])
                  if a.get("integrator") != b.get("integrator")]  # where each further fit begins
        for ax in axes:
            for x in starts:
                ax.axvline(x, color="0.6", lw=0.8, ls="--")
        axes[0].set_title(f"loss ({result.gradient}; {' | '.join(sel['fits'])}, kept {sel['chosen']})")
    units = {"density": "kg/m²", "stretch_stiffness": "N/m", "bend_stiffness": "N·m", BLEND: "0 euler, 1 bdf2"}
    for ax, n in zip(axes[1:], params):
        values = [r.get(n, math.nan) for r in result.history]
        (ax.plot if n == BLEND else ax.semilogy)(it, values)
        ax.set_xlabel("iteration")
        ax.set_title(f"{n} [{units[n]}]")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
