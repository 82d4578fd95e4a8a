"""The material stage's settings: :class:`PhysicsConfig` (every field is a ``fit-physics`` option,
:func:`physavatar.stages.base.option`) and the settings ``physavatar run`` fits with."""

from __future__ import annotations

from dataclasses import dataclass

from ...errors import PhysavatarError
from ...sim.material import FIT_REST_FRICTION, FIT_REST_SHAPE, REST_SHAPES
from ..base import option, options

GRADIENTS = ("fd", "exact")
SELECT_SHAPE_WEIGHT = True  # fit-physics --select-shape-weight: the default since session 36
INTEGRATORS = ("auto", "euler", "bdf2")


def _at_least(n: int, problem: str):
    return lambda v: None if v >= n else problem


@dataclass(frozen=True)
class PhysicsConfig:
    """Everything that defines a material fit (saved as config.json beside material.json).

    Attributes:
        gradient: ``"exact"`` (forward sensitivities + Levenberg–Marquardt) or ``"fd"`` (the
            paper: finite differences + Adam).
        window: frames fitted (the paper: 24); start: the window's first frame.
        iterations: optimizer iterations (None: 100 with fd, 15 with exact).
        init: the initial material: ``"far"`` (:func:`~.parameters.far_material`), a preset or a
            material JSON; density: its density prior ρ [kg/m²] (None: the initial material's).
        fit_density: fit ρ too (only κs/ρ and κb/ρ are identifiable).
        noise_mm, seed: Gaussian noise added to the reference (benchmarks) and its seed.
        workers: processes for the fd simulations (does not change the result).
        friction, newton_tol, substeps: the fitting simulations' friction coefficient, Newton
            tolerance [m/s] and implicit steps per frame.
        integrator: ``"auto"`` (exact: fit in implicit Euler, BDF2 and their blend, keep the
            lowest objective; fd: implicit Euler), ``"euler"`` or ``"bdf2"``.
        max_vertices: fit on a coarse proxy of at most this many vertices when the garment has
            more (0: always the full garment).
        shape_weight: weight of the local-shape residuals (None: 3 with exact, 0 with fd).
        rest_friction: with ``rest_shape`` "equilibrium", the rest solve's equilibria hold the
            garment with static friction (Material.rest_friction, sim.rest.StaticFriction;
            session 36); the material records it, so animate/evaluate solve the same.
        select_shape_weight: with exact gradients and ``shape_weight`` None, fit with weight 3
            and with 0 and keep the one that predicts the frames after the window (up to a
            window's length of them) better (stage.select_shape_weight; session 36).
        contact_offset: the cloth's contact thickness [m] (Material.contact_offset, ipctk's d_min);
            None: estimated from the start frame, the garment's distance to the body where it
            rests on it (sim.offset.estimate_contact_offset; 0 when it does not rest on it at
            one distance, as a garment made in place with a design clearance); 0: none.
        rest_shape: the garment's stress-free shape in the fitting simulations: ``"template"``
            (the start frame, loaded by gravity) or ``"equilibrium"`` (sim.rest.equilibrium_rest:
            the rest shape whose static equilibrium is the start frame, for the material of a first
            fit with the template; then fitted again from that material; the material records it
            and animate/evaluate/the tracker compute the same rest for it; the default since session 28;
            a start frame not at rest keeps the first fit).
    """

    gradient: str = option("exact", "fd (the paper: finite differences + Adam) or exact (sensitivities + "
                                     "Gauss-Newton)", choices=GRADIENTS)
    window: int = option(24, "frames fitted (the paper: 24)", check=_at_least(2, "needs at least 2 frames"))
    start: int = option(0, "first frame of the window (simulated from rest there)")
    iterations: int | None = option(None, "optimizer iterations (default: 100 fd, 15 exact)",
                                    check=_at_least(1, "must be at least 1"))
    init: str = option("far", "initial material: a material JSON, a preset (silk, cotton, denim) or 'far'")
    fit_density: bool = option(False, "also fit rho (only ks/rho, kb/rho are identifiable)", flag="--fit-density")
    density: float | None = option(None, "density prior rho in kg/m^2 (default: the initial material's)",
                                   check=lambda v: None if v > 0 else "must be positive")
    noise_mm: float = option(0.0, "Gaussian noise (mm) added to the reference (benchmarks)", flag="--noise-mm",
                             check=lambda v: None if v >= 0 else "must be >= 0")
    workers: int = option(2, "processes for the fd simulations", hash=False)
    seed: int = option(0, "seed of --noise-mm")
    friction: float = option(0.2, "cloth-body friction coefficient of the simulator (0 = off)",
                             check=lambda v: None if v >= 0 else "must be >= 0")
    newton_tol: float = option(1e-4, "Newton tolerance of the fitting simulations [m/s]", flag="--newton-tol",
                               check=lambda v: None if v > 0 else "must be positive")
    substeps: int = option(1, "implicit steps per frame of the fitting simulations (more: less "
                              "time-discretisation error, proportionally slower)",
                           check=_at_least(1, "must be at least 1"))
    integrator: str = option("auto", "time integrator of the fitting simulations: auto (exact: fit in euler, in "
                                     "bdf2 and in their blend with its weight fitted too, keep the best; fd: "
                                     "euler), euler or bdf2. The material records it and simulate/animate use it "
                                     "(docs/physics.md)", choices=INTEGRATORS)
    max_vertices: int = option(1200, "fit on a coarse proxy of at most this many vertices when the garment has "
                                     "more (0 = always the full garment; docs/physics.md)", flag="--max-vertices",
                               check=lambda v: None if v == 0 or v >= 20 else "must be 0 (no proxy) or at least 20")
    shape_weight: float | None = option(None, "weight of the local-shape residuals next to L_sim (default: 3 "
                                              "with exact, 0 = the paper's L_sim with fd; docs/physics.md)",
                                        flag="--shape-weight", check=lambda v: None if v >= 0 else "must be >= 0")
    rest_friction: bool = option(FIT_REST_FRICTION,
                                 "with --rest-shape equilibrium: the rest solve holds the garment with static friction "
                                 "(--friction, anchored at the start frame) instead of frictionless; the material "
                                 "records it (docs/physics.md)", flag="--rest-friction")
    select_shape_weight: bool = option(SELECT_SHAPE_WEIGHT,
                                       "without --shape-weight (exact): fit with the shape term (weight 3) and without "
                                       "it, and keep weight 0 only when it predicts the frames after the window better "
                                       "in a sign test (a second fit; docs/physics.md)", flag="--select-shape-weight")
    contact_offset: float | None = option(None, "cloth contact thickness in m, kept between cloth and body "
                                                "(default: estimated from the start frame where the garment "
                                                "rests on the body; 0 = none; docs/physics.md)",
                                          flag="--contact-offset",
                                          check=lambda v: None if 0 <= v < 0.05 else "must be in [0, 0.05) m")
    rest_shape: str = option(FIT_REST_SHAPE, "the garment's rest shape in the fitting simulations: template (the start "
                                          "frame, loaded by gravity) or equilibrium (the shape whose static "
                                          "equilibrium is the start frame; a second fit; docs/physics.md)",
                             flag="--rest-shape", choices=REST_SHAPES)

    def __post_init__(self) -> None:
        # the same checks, and messages, as the command line's (a config made in Python)
        for s in options(type(self)):
            value = getattr(self, s.path)
            if value is None:
                continue
            if s.choices is not None and value not in s.choices:
                allowed = ", ".join(map(str, s.choices[:-1])) + f" or {s.choices[-1]}"
                raise PhysavatarError(None, f"option {s.flag}: {value!r} is not {allowed}")
            problem = s.check(value) if s.check is not None else None
            if problem:
                raise PhysavatarError(None, f"option {s.flag}: {problem}")

    @property
    def selects_integrator(self) -> bool:
        """``integrator="auto"`` with exact gradients: fit in every model and keep the best."""
        return self.integrator == "auto" and self.gradient == "exact"

    @property
    def fitting_integrator(self) -> str:
        """The integrator of the (first) fit: ``auto`` means implicit Euler first (fd: only)."""
        return "euler" if self.integrator == "auto" else self.integrator


def pipeline_config(quick: bool = False) -> PhysicsConfig:
    """The settings ``physavatar run`` fits with: a 12-frame window and 8 iterations, or with
    ``quick`` 6 frames and 3 iterations (CPU budgets; docs/physics.md)."""
    return PhysicsConfig(window=6, iterations=3) if quick else PhysicsConfig(window=12, iterations=8)
