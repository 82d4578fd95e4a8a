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
  local shape w·L r (:func:`fit_residuals`, :data:`SHAPE_WEIGHT`), where bending shows when the
  ground truth comes from another simulator.

Units and the mapping of the paper's step sizes and ranges: docs/physics.md.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import math
import multiprocessing
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np
import scipy.sparse as sp

from ..errors import PhysavatarError
from ..geometry import submesh
from ..optim import Adam, lm_step
from ..sim import Material, SimSettings, preset
from ..sim.material import CODIM_BASE_POISSON, CODIM_BASE_THICKNESS, CODIM_BASE_YOUNG
from ..sim.sensitivity import BLEND, Rollout
from ..sim.sensitivity import rollout as sim_rollout

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
PAPER_WINDOW = 24  # frames (App. A.3.1)
# Newton tolerance of the fitting simulations [m/s]. At the simulator's default (1e-3) the
# solver error alone leaves L_sim ~15 % above the noise floor at the true material on the demo
# dress and makes it rough at the 1 % parameter scale; 1e-5 puts it at the floor.
FIT_NEWTON_TOL = 1e-5
# Weight w of the local-shape residuals w·L(x − x̂) next to Eq. 6's x − x̂ (fit_residuals) in the
# exact estimator's objective. Under model error (ground truth at 2 steps per frame, fits at 1)
# Eq. 6 alone is ~flat in κb (1 % over three decades) and LM put κb at −64 % (cotton) to its
# bound; the shape residuals have their minimum near the true κb. w = 3 measured in
# docs/physics.md ("Local shape"); 0 is the paper's L_sim.
SHAPE_WEIGHT = 3.0
# Where the fit of the BDF2 blend γ may start (fit_selecting_integrator): the one of these with
# the lowest objective at the implicit-Euler stiffnesses. From a fixed start (0.5), LM stopped
# where it began against the other simulator (denim): under contact the objective is rough at
# the 0.05 scale in γ, so four trust-region halvings were all rejected (docs/physics.md).
BLEND_STARTS = (0.25, 0.5, 0.75, 1.0)
# The fits fit_selecting_integrator makes, in this order: implicit Euler; BDF2 (γ = 1) from its
# estimate; the blend with γ fitted. BDF2 itself stays a candidate because LM on γ can stop short
# of γ = 1 on a rough objective (the other simulator, denim: γ 0.83, objective 1.549 against
# 1.514 at γ = 1, held-out 0.133 against 0.102; docs/physics.md).
MODELS = ("euler", "bdf2", "bdf2_blend")


def fit_settings(**changes) -> SimSettings:
    """The simulator settings material estimation uses by default (SimSettings + FIT_NEWTON_TOL).

    The fits keep the ∞-norm stopping rule (newton_norm="max") that FIT_NEWTON_TOL was measured
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


# -- problem data --------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class PhysicsData:
    """What material estimation fits to.

    Attributes:
        reference: [T, N, 3] tracked garment vertices (frame 0 is the initial state, at rest).
        faces: [F, 3] garment triangles.
        boundary: [K] Dirichlet vertex ids (driven by ``boundary_targets``).
        collider: [T, Nb, 3] body vertices per frame, or None (no body).
        collider_faces: [Fb, 3] body triangles, or None.
        fps: frames per second of ``reference``.
        rest: [N, 3] the garment's stress-free shape (default ``reference[0]``).
        boundary_targets: [T, K, 3] boundary positions per frame (default: their tracked
            positions ``reference[:, boundary]``; an attachment to the body also works).
        targets_tracked: the boundary targets are the tracked positions (set when they were
            defaulted); :meth:`with_noise` then perturbs them as tracking noise would.
        initial: [N, 3] the state the simulation starts from, at rest (default: the reference
            frame 0, Algorithm 1). A known clean start (the template at rest) avoids feeding
            tracking noise into the first step as strain and near-contacts.
    """

    reference: np.ndarray
    faces: np.ndarray
    boundary: np.ndarray
    collider: np.ndarray | None = None
    collider_faces: np.ndarray | None = None
    fps: float = 25.0
    rest: np.ndarray | None = None
    boundary_targets: np.ndarray | None = None
    targets_tracked: bool = False
    initial: np.ndarray | None = None

    def __post_init__(self):
        ref = np.asarray(self.reference, dtype=np.float64)
        if ref.ndim != 3 or ref.shape[2] != 3 or len(ref) < 2:
            raise PhysavatarError(None, f"reference must be [T >= 2, N, 3], got {ref.shape}")
        if not np.all(np.isfinite(ref)):
            raise PhysavatarError(None, "reference vertices contain non-finite values")
        object.__setattr__(self, "reference", ref)
        object.__setattr__(self, "faces", np.asarray(self.faces, dtype=np.int64).reshape(-1, 3))
        b = np.unique(np.asarray(self.boundary, dtype=np.int64).ravel())
        object.__setattr__(self, "boundary", b)
        if self.rest is None:
            object.__setattr__(self, "rest", ref[0].copy())
        if self.boundary_targets is None:
            object.__setattr__(self, "boundary_targets", ref[:, b])
            object.__setattr__(self, "targets_tracked", True)
        if self.collider is not None:
            c = np.asarray(self.collider, dtype=np.float64)
            if c.ndim != 3 or len(c) != len(ref):
                raise PhysavatarError(None, f"collider must be [T={len(ref)}, Nb, 3], got {c.shape}")
            object.__setattr__(self, "collider", c)
        if not self.fps > 0:
            raise PhysavatarError(None, f"fps must be positive, got {self.fps}")

    @property
    def frames(self) -> int:
        return len(self.reference)

    def window(self, start: int = 0, length: int = PAPER_WINDOW) -> "PhysicsData":
        """Frames [start, start + length) (the paper fits 24 frames, App. A.3.1)."""
        stop = min(self.frames, start + max(2, length))
        sl = slice(start, stop)
        return dataclasses.replace(
            self, reference=self.reference[sl],
            collider=None if self.collider is None else self.collider[sl],
            boundary_targets=self.boundary_targets[sl],
        )

    def with_noise(self, sigma_m: float, seed: int = 0) -> "PhysicsData":
        """Gaussian noise of std ``sigma_m`` [m] per coordinate on the reference (benchmarks).

        The boundary targets (the simulation's input) stay clean unless they are the tracked
        positions (``targets_tracked``), in which case they carry the same noise.
        """
        if sigma_m <= 0:
            return self
        rng = np.random.default_rng(seed)
        ref = self.reference + rng.normal(0.0, sigma_m, self.reference.shape)
        return dataclasses.replace(
            self, reference=ref,
            boundary_targets=ref[:, self.boundary] if self.targets_tracked else self.boundary_targets,
        )


# -- the start state ------------------------------------------------------------------------------

# [m] a start vertex closer than this to the body is pushed out to START_CLEARANCE (the barrier
# is infinite at contact and stiff far inside d̂; another simulator's cloth may lie on the skin)
START_MIN_GAP = 2e-4
START_CLEARANCE = 1e-3  # = the fits' d̂


def clear_start(data: PhysicsData, source=None, frame: int = 0,
                sequence: PhysicsData | None = None) -> tuple[PhysicsData, dict]:
    """``data`` with an initial state the simulator can start from, and what was done to it.

    The simulation of a window starts from ``data.initial`` (default the reference frame 0) and
    IPC needs that state free of garment–body intersections, at a positive distance (its CCD
    assumes it; from a crossing start the solver runs but its steps are not valid, and the fit
    would follow a non-converged simulation without a word). Tracked garments and other
    simulators' output need not be: a simulator that only keeps the cloth's *vertices* out of the
    body lets limbs pass through the faces between them (benchmarks/foreign_cloth.py on the 7-cm
    dress: 160–700 crossing triangle pairs in every walk frame after the first).

    A start closer than :data:`START_MIN_GAP` or crossing the body is pushed out along the body
    normal to :data:`START_CLEARANCE` (garment.push_out; the boundary vertices stay at their
    targets). When it still crosses, this raises a :class:`PhysavatarError` naming ``source``, the
    ``frame`` (``data``'s first frame in ``sequence``) and the crossing pairs, with the frames of
    ``sequence`` (default ``data``, numbered from ``frame``) that are free of crossings, for
    ``--start``. Returns (data with ``initial`` set, info dict for material.json).
    """
    from ..garment.garment import body_clearance, push_out
    from ..geometry import count_intersections

    x0 = np.asarray(data.reference[0] if data.initial is None else data.initial, dtype=np.float64)
    info = {"frame": int(frame), "crossing_pairs": 0, "min_gap_mm": None, "pushed_vertices": 0, "max_push_mm": 0.0}
    if data.collider is None or data.collider_faces is None:
        return dataclasses.replace(data, initial=x0), info
    body, bfaces = data.collider[0], data.collider_faces
    crossing = count_intersections(x0, data.faces, body, bfaces)
    gap = body_clearance(x0, data.faces, body, bfaces)
    info.update(crossing_pairs=int(crossing), min_gap_mm=1e3 * gap)
    if crossing == 0 and gap >= START_MIN_GAP:
        return dataclasses.replace(data, initial=x0), info
    moved, _ = push_out(x0, data.faces, [(body, bfaces)], START_CLEARANCE)
    moved[data.boundary] = x0[data.boundary]
    left = count_intersections(moved, data.faces, body, bfaces)
    if left:
        seq, first = (sequence, 0) if sequence is not None else (data, frame)
        clean = [first + f for f in range(min(seq.frames, 200))
                 if not count_intersections(seq.reference[f], seq.faces, seq.collider[f], bfaces)]
        where = (f"frames free of crossings: {clean[:12]}" + (" ..." if len(clean) > 12 else "")
                 if clean else "no frame is free of crossings")
        raise PhysavatarError(source, f"the garment crosses the body at frame {frame} ({crossing} intersecting "
                                      f"triangle pairs, {left} after pushing it out): the simulation needs an "
                                      f"intersection-free start; {where}")
    step = np.linalg.norm(moved - x0, axis=1)
    info.update(pushed_vertices=int(np.count_nonzero(step > 0)), max_push_mm=1e3 * float(step.max()),
                min_gap_after_mm=1e3 * body_clearance(moved, data.faces, body, bfaces))
    return dataclasses.replace(data, initial=moved), info


# -- a coarse simulation proxy of a big garment (stages/proxy.py) ------------------------------

PROXY_MAX_VERTICES = 400  # fit-physics default: garments above this are fitted on a proxy
PROXY_CLEARANCE = 0.003  # [m] the proxy's smallest distance to the body at rest (> d̂ = 1 mm)


def on_proxy(data: PhysicsData, proxy) -> PhysicsData:
    """``data`` moved onto a :class:`~physavatar.stages.proxy.GarmentProxy` of its garment.

    Every fine per-vertex sequence maps by the proxy's barycentric coordinates at rest: the
    reference (tracked positions), the rest shape, the initial state, and the proxy's boundary
    targets — the map of the fine positions with the fine boundary vertices at their targets
    (the tracked boundary, or a prescribed attachment). The body collider is unchanged. Rest
    shape and initial state are then pushed off the body frame 0 to ``PROXY_CLEARANCE`` where
    the proxy's chords dip into it (a few mm; the reference is not moved).
    """
    ref = proxy.map(data.reference)
    b = np.asarray(proxy.boundary, dtype=np.int64)
    driven = data.reference.copy()
    driven[:, data.boundary] = data.boundary_targets
    targets = proxy.map(driven)[:, b]
    rest = proxy.map(data.rest)
    initial = ref[0] if data.initial is None else proxy.map(data.initial)
    offset = 0.0
    if data.collider is not None and data.collider_faces is not None:
        # the proxy's flat triangles cut chords through the fine surface; over a convex body
        # part they can dip into it at rest (IPC needs an intersection-free start, and a
        # trapped proxy cannot sag like the garment): push them out to PROXY_CLEARANCE
        from ..garment.garment import push_out

        moved, _ = push_out(initial, proxy.faces, [(data.collider[0], data.collider_faces)], PROXY_CLEARANCE)
        moved[b] = initial[b]  # the attachment stays where the fine one is
        offset = moved - initial
    return PhysicsData(
        reference=ref, faces=proxy.faces, boundary=b, collider=data.collider, collider_faces=data.collider_faces,
        fps=data.fps, rest=rest + offset, boundary_targets=targets, targets_tracked=data.targets_tracked,
        initial=initial + offset,
    )


# -- simulation with forward sensitivities (physavatar.sim.sensitivity) ---------------------------


def _with_log_params(material: Material, names, log_values) -> Material:
    """``material`` with the parameters ``names`` set from θ (log values; the blend γ as is)."""
    return dataclasses.replace(material, **{n: float(min(max(v, 0.0), 1.0) if n == BLEND else math.exp(v))
                                            for n, v in zip(names, log_values)})


def _theta(material: Material, names) -> np.ndarray:
    return np.array([getattr(material, n) if n == BLEND else math.log(getattr(material, n)) for n in names])


def rollout(data: PhysicsData, material: Material, settings: SimSettings | None = None,
            parameters=None, substeps: int = 1) -> Rollout:
    """Simulate ``data``'s window with ``material`` from ``data.initial`` (default the reference
    frame 0) at rest (:func:`physavatar.sim.sensitivity.rollout`). Returns a :class:`Rollout`.

    Args:
        parameters: names (from :data:`PARAMETERS` and :data:`BLEND`) to differentiate with
            respect to (in log space; γ as is), or None for a plain simulation.
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
    mostly shows as such a drift, in which κb is nearly invisible (its effect on Eq. 6 is ~1 %
    of a 1-vs-2-steps-per-frame mismatch on the dress); bending shows in the local shape.
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


def _objective(data: PhysicsData, material: Material, settings: SimSettings | None = None, substeps: int = 1,
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
    return _objective(data, material, settings, substeps)


# -- results -------------------------------------------------------------------------------------


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
    proxy: dict | None = None  # the coarse proxy fitted on (stages/proxy.py), if any
    shape_weight: float = 0.0  # weight of the local-shape residuals (fit_residuals)
    objective: float | None = None  # what was minimised (= loss when shape_weight is 0)
    model_selection: dict | None = None  # fit_selecting_integrator: both fits and the choice
    start_state: dict | None = None  # clear_start: crossings and gap of the start frame, what was pushed

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
        }


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


# -- the paper's estimator: finite differences + Adam --------------------------------------------

_WORKER: dict = {}


def _worker_init(data, material, settings, names, substeps, shape_weight=0.0):
    _WORKER.update(data=data, material=material, settings=settings, names=names, substeps=substeps,
                   shape_weight=shape_weight)


def _worker_simulate(log_values):
    """One FD simulation in a pool worker: (loss, positions) or (inf, None) if it fails."""
    w = _WORKER
    m = _with_log_params(w["material"], w["names"], log_values)
    try:
        r = rollout(w["data"], m, w["settings"], substeps=w["substeps"])
    except (FloatingPointError, np.linalg.LinAlgError, RuntimeError):
        return math.inf, None
    res, _ = fit_residuals(r.positions, w["data"], w["shape_weight"])
    return float(res @ res), r.positions.astype(np.float32)


@contextlib.contextmanager
def _single_threaded_children():
    """Spawned workers inherit the environment: one BLAS / numba / OpenMP thread each, so two
    workers on two cores do not oversubscribe them (set before the children import numpy)."""
    keys = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")
    old = {k: os.environ.get(k) for k in keys}
    os.environ.update({k: "1" for k in keys})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class _Evaluator:
    """Runs batches of simulations: a spawn-context process pool, or inline with workers=0/1."""

    def __init__(self, data, material, settings, names, substeps, workers, shape_weight=0.0):
        self.workers = workers
        self.pool = None
        if workers > 1:
            with _single_threaded_children():
                self.pool = concurrent.futures.ProcessPoolExecutor(
                    max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_worker_init, initargs=(data, material, settings, names, substeps, shape_weight))
                # start the workers now, while the environment says one thread each
                list(self.pool.map(_noop, range(workers)))
        else:
            _worker_init(data, material, settings, names, substeps, shape_weight)

    def map(self, points):
        if self.pool is None:
            return [_worker_simulate(p) for p in points]
        return list(self.pool.map(_worker_simulate, points))

    def close(self):
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)


def _noop(_):
    return None


def _bounds(names):
    """Bounds of θ: log :data:`BOUNDS`, and [0, 1] for the blend γ."""
    lo = np.array([0.0 if n == BLEND else math.log(BOUNDS[n][0]) for n in names])
    hi = np.array([1.0 if n == BLEND else math.log(BOUNDS[n][1]) for n in names])
    return lo, hi


def fit_fd(data: PhysicsData, initial: Material, settings: SimSettings | None = None,
           iterations: int = PAPER_ITERATIONS, fit_density: bool = False, workers: int = 2,
           substeps: int = 1, callback: Callable | None = None, shape_weight: float = 0.0) -> FitResult:
    """Algorithm 1: forward finite differences (Eq. 7) and Adam, in log space.

    Each iteration simulates θ and θ + δ_p e_p for every fitted p (in parallel over ``workers``
    processes), takes ΔL/δ as the gradient, and makes one Adam step (lr cosine-annealed from
    0.1 to 0.04 on log κ, the paper's values mapped at its start point; module constants).
    The result is the best iterate seen (as the official driver keeps). The residual Jacobian
    of the last iteration's differences gives the confidence intervals. ``shape_weight``: as in
    :func:`fit_exact` (0, the paper's L_sim, by default).
    """
    settings = settings or fit_settings()
    names = PARAMETERS if fit_density else PARAMETERS[1:]
    theta = np.array([math.log(getattr(initial, n)) for n in names])
    delta = np.array([FD_STEP[n] for n in names])
    lr0 = np.array([ADAM_LR[n] for n in names])
    lo, hi = _bounds(names)
    adam = Adam({"theta": theta.shape})
    t_start = time.perf_counter()
    history = []
    best = (math.inf, theta.copy(), None, None, math.inf)
    sims = 0
    ev = _Evaluator(data, initial, settings, names, substeps, workers, shape_weight)
    ref = data.reference
    try:
        for it in range(iterations):
            points = [theta.copy()] + [theta + delta[p] * np.eye(len(names))[p] for p in range(len(names))]
            results = ev.map(points)
            sims += len(points)
            losses = np.array([r[0] for r in results])
            loss = losses[0]
            if not np.isfinite(loss):
                raise PhysavatarError(None, f"simulation failed at {dict(zip(names, np.exp(theta)))}")
            grad = np.where(np.isfinite(losses[1:]), (losses[1:] - loss) / delta, 0.0)
            lsim = loss if shape_weight <= 0 else trajectory_loss(results[0][1].astype(np.float64), ref)
            if loss < best[0]:
                fd_jac = None
                if all(r[1] is not None for r in results):
                    base = results[0][1].astype(np.float64)
                    fd_jac = np.stack([(r[1].astype(np.float64) - base)[1:].ravel() / d
                                       for r, d in zip(results[1:], delta)], axis=1)
                best = (loss, theta.copy(), fd_jac, (results[0][1].astype(np.float64) - ref)[1:].ravel(), lsim)
            row = _history_row(it, lsim, data, names, theta, t_start, sims, loss)
            history.append(row)
            if callback is not None:
                callback(row)
            # Adam (bias-corrected) with the official driver's cosine learning-rate schedule
            lr = lr0 * (ADAM_LR_FINAL_FRACTION + (1 - ADAM_LR_FINAL_FRACTION) * 0.5 * (1 + math.cos(math.pi * it / iterations)))
            theta = np.clip(adam.step({"theta": theta}, {"theta": grad}, lr)["theta"], lo, hi)
    finally:
        ev.close()
    objective, theta_best, fd_jac, resid, loss = best
    material = dataclasses.replace(_with_log_params(initial, names, theta_best), name="fitted (fd)",
                                   integrator=settings.integrator)
    intervals, stds = ratio_intervals(fd_jac, resid, list(names), material) if fd_jac is not None else ({}, {})
    return FitResult(material, initial, float(loss), rms_mm(loss, data), iterations, sims,
                     time.perf_counter() - t_start, "fd", names, history, intervals, stds, data.frames,
                     _settings_dict(settings, substeps, data.fps), shape_weight=shape_weight, objective=float(objective))


def _history_row(it, loss, data, names, theta, t_start, sims, objective=None):
    row = {"iteration": it, "loss": float(loss), "rms_mm": rms_mm(loss, data),
           "objective": float(loss if objective is None else objective)}
    for n, v in zip(names, theta):
        row[n] = float(v if n == BLEND else math.exp(v))
    row["wall_time_s"] = time.perf_counter() - t_start
    row["simulations"] = sims
    return row


def _settings_dict(settings, substeps, fps):
    d = dataclasses.asdict(settings)
    d["substeps"] = substeps
    d["dt"] = 1.0 / (fps * substeps)  # the step the simulations took (rollout sets it from the data's fps)
    d["gravity"] = list(d["gravity"])
    return d


# -- exact gradients: forward sensitivities + Levenberg–Marquardt --------------------------------


def fit_exact(data: PhysicsData, initial: Material, settings: SimSettings | None = None,
              iterations: int = 15, fit_density: bool = False, substeps: int = 1,
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
    lo, hi = _bounds(names)
    theta = np.clip(_theta(initial, names), lo, hi)
    t_start = time.perf_counter()
    sims = 0
    history = []

    def evaluate(th):
        m = _with_log_params(initial, names, th)
        r = rollout(data, m, settings, parameters=names, substeps=substeps)
        res, J = fit_residuals(r.positions, data, shape_weight, r.jacobian)
        return float(res @ res), res, J, trajectory_loss(r.positions, data.reference)

    loss, res, J, lsim = evaluate(theta)
    sims += 1
    lam = 1e-3
    rejected = 0
    row = _history_row(0, lsim, data, names, theta, t_start, sims, loss)
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
        row = _history_row(it, lsim, data, names, theta, t_start, sims, loss)
        row["accepted"] = bool(improved)
        history.append(row)
        if callback is not None:
            callback(row)
        rejected = 0 if improved else rejected + 1
        if improved and rel < tolerance:
            break
        if rejected >= max_rejections or radius < 1e-3:
            break  # no better point within a shrinking region: at a (local) minimum
    material = dataclasses.replace(_with_log_params(initial, names, theta), name="fitted (exact)",
                                   integrator=settings.integrator)
    intervals, stds = ratio_intervals(J, res, list(names), material)
    return FitResult(material, initial, float(lsim), rms_mm(lsim, data), len(history) - 1, sims,
                     time.perf_counter() - t_start, "exact", names, history, intervals, stds, data.frames,
                     _settings_dict(settings, substeps, data.fps), shape_weight=shape_weight, objective=float(loss))


def fit_selecting_integrator(data: PhysicsData, initial: Material, settings: SimSettings | None = None,
                             iterations: int = 15, fit_density: bool = False, substeps: int = 1,
                             callback: Callable | None = None, shape_weight: float = SHAPE_WEIGHT) -> FitResult:
    """Fit in implicit Euler, in BDF2, and in their blend with γ fitted; keep the lowest objective.

    The fitted material is the best one *for the simulation model it was fitted in* (time
    integrator and step): under model error the models prefer different materials. Implicit
    Euler at one step per frame (the paper's) damps the motion numerically; a ground truth from
    a less damped simulator (or real cloth) is fitted much better by BDF2 at the same cost per
    step. Choosing between those two by the fitted window's objective picked the model that
    predicted a held-out motion worse in 2 of 12 benchmark cases (docs/physics.md, "Which
    simulation model"), and in both the objective was lowest between them. So a third fit makes
    the choice continuous: (κs, κb, γ) in the blend of the two (Material.bdf2_blend; γ = 0 is
    implicit Euler, 1 BDF2), from the implicit-Euler estimate and the γ of :data:`BLEND_STARTS`
    with the lowest objective there (4 plain simulations). The fits run in the order of
    :data:`MODELS`, the BDF2 ones from the implicit-Euler estimate. The result is the chosen fit;
    its material records the integrator and γ (which :func:`physavatar.sim.simulate` then
    uses), ``model_selection`` every fit and the scan; simulations and wall time count all.
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
                    "objective": [_objective(data, m, bdf2, substeps, shape_weight) for m in candidates]}
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
        return fit(data, initial, settings, iterations or 15, fit_density, substeps, callback=callback,
                   shape_weight=shape_weight)
    raise PhysavatarError(None, f"gradient must be 'fd' or 'exact', got {gradient!r}")


# -- folders in, folders out ---------------------------------------------------------------------


def load_physics_data(folder: str | Path) -> PhysicsData:
    """A tracked folder (``tracked.npz``: vertices [T, V, 3], faces, labels) or a capture with
    ``ground_truth/meshes.npz``; the boundary flags come from the capture template (the
    tracked folder's ``boundary`` array, or its capture's ``template/mesh.ply``). A folder with
    ``garment_sequence.npz`` (``physavatar simulate``'s output), or an .npz without ``labels``
    given by name, is a garment sequence (:func:`load_garment_sequence`).

    The garment is every vertex with label ≥ 1 (the first garment when there are several);
    the body (label 0) is the collider, and garment faces are those with all three corners on
    the garment. The garment's rest shape is the template's (frame-1 mesh); a ``tracked.npz``
    with no template to be found (another tool's sequence) takes its frame 0 as the rest shape
    and its own ``boundary`` flags, or none. A garment without boundary (Dirichlet) vertices
    is simulated as held by contact and friction alone.
    """
    from ..data.garment_sequence import FILE as GARMENT_SEQUENCE
    from ..data.tracked import FILE as TRACKED, TrackedSequence
    from ..files import load_npz

    folder = Path(folder)
    z = None  # the tracked arrays, when a file given by name was read already
    if folder.is_file() and folder.suffix == ".npz":
        z = load_npz(folder)
        if "labels" not in z:
            return load_garment_sequence(folder, z)
        tracked, folder = folder, folder.parent  # a tracked.npz-style file given by name
    elif not folder.is_dir():
        raise PhysavatarError(folder, "not a folder or .npz (expected a tracked folder, a capture or a garment sequence)")
    else:
        tracked = folder / TRACKED
        if not tracked.is_file() and not (folder / "ground_truth" / "meshes.npz").is_file() \
                and (folder / GARMENT_SEQUENCE).is_file():
            return load_garment_sequence(folder / GARMENT_SEQUENCE)
    if tracked.is_file():
        src = tracked
    else:
        src = folder / "ground_truth" / "meshes.npz"
        if not src.is_file():
            raise PhysavatarError(folder, "none of tracked.npz, ground_truth/meshes.npz, garment_sequence.npz found")
    # a capture's ground-truth meshes have the tracked format (its boundary flags are the template's)
    seq = TrackedSequence.from_arrays(load_npz(src) if z is None else z, src,
                                      require=("vertices", "faces", "labels"), min_frames=2)
    boundary = seq.boundary if src == tracked else None
    rest = None
    fps = 25.0 if seq.fps is None else seq.fps
    template_dir = folder
    verts = np.asarray(seq.vertices, dtype=np.float64)
    faces, labels = seq.faces, seq.labels
    ply = None
    if boundary is None or rest is None:
        ply = template_dir / "template" / "mesh.ply"
        if not ply.is_file() and (template_dir / "capture").is_dir():
            ply = template_dir / "capture" / "template" / "mesh.ply"
        if not ply.is_file() and (template_dir / "config.json").is_file():
            # a tracking folder records the capture it tracked
            from ..files import read_json

            cap = read_json(template_dir / "config.json").get("capture")
            if cap:
                ply = Path(cap) / "template" / "mesh.ply"
        if not ply.is_file() and src.name == "tracked.npz":
            rest = verts[0]  # a sequence on its own: its first frame is the template
            ply = None
        elif not ply.is_file():
            raise PhysavatarError(template_dir, "no template/mesh.ply with the garment's rest shape and boundary flags")
    if ply is not None and (boundary is None or rest is None):
        from ..files import read_ply

        try:
            mesh = read_ply(ply)
        except PhysavatarError:
            raise
        except Exception as e:  # a malformed PLY of any kind
            raise PhysavatarError(ply, f"cannot read template ({e})") from None
        if len(mesh.vertices) != len(labels):
            raise PhysavatarError(ply, f"template has {len(mesh.vertices)} vertices, {src.name} has {len(labels)}")
        if boundary is None:
            boundary = np.asarray(mesh.vertex_data.get("boundary", np.zeros(len(labels)))).astype(bool)
        rest = mesh.vertices
    garment_ids = sorted(set(labels.tolist()) - {0})
    if not garment_ids:
        raise PhysavatarError(src, "no garment vertices (labels >= 1)")
    gidx, gfaces = submesh(faces, labels == garment_ids[0])
    bidx, bfaces = submesh(faces, labels == 0)
    gboundary = np.flatnonzero(boundary[gidx]) if boundary is not None else np.zeros(0, np.int64)
    return PhysicsData(
        reference=verts[:, gidx], faces=gfaces, boundary=gboundary,
        collider=verts[:, bidx] if len(bidx) else None, collider_faces=bfaces if len(bidx) else None,
        fps=fps, rest=np.asarray(rest, np.float64)[gidx],
    )


def load_garment_sequence(path: str | Path, z=None) -> PhysicsData:
    """A garment simulated on a moving body, as ``physavatar simulate`` writes it
    (``garment_sequence.npz``) and as any cloth simulator can: ``vertices`` [T, N, 3] (the garment),
    ``faces`` [F, 3]; optional ``boundary`` (per-vertex flags [N] or vertex ids [K]: the attached
    vertices, none = held by contact alone), ``body_vertices`` [T, Nb, 3] with ``body_faces``
    (the collider), ``fps`` (25) and ``rest_vertices`` [N, 3] (the stress-free shape; default
    frame 0)."""
    from ..data.garment_sequence import GarmentSequence
    from ..files import load_npz

    path = Path(path)
    seq = GarmentSequence.from_arrays(load_npz(path) if z is None else z, path)
    return PhysicsData(reference=seq.vertices, faces=seq.faces, boundary=seq.boundary, collider=seq.body_vertices,
                       collider_faces=seq.body_faces, fps=seq.fps, rest=seq.rest_vertices)


def write_outputs(out: str | Path, result: FitResult) -> None:
    """material.json, fit_log.csv and fit.png in ``out`` (atomic writes)."""
    from ..data.material import FILE as MATERIAL, FittedMaterial
    from ..files import atomic_path, write_text_atomic

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    FittedMaterial.from_json(result.to_json()).save(out / MATERIAL)
    # the parameters of every row: with the integrator selection, the BDF2 fit's rows add γ
    params = [n for n in PARAMETERS + (BLEND,) if n in result.fitted or any(n in r for r in result.history)]
    cols = ["iteration", "loss", "rms_mm"] + params + ["wall_time_s", "simulations"]
    if any("integrator" in row for row in result.history):
        cols.append("integrator")  # fit_selecting_integrator: implicit Euler's iterations, then BDF2's
    lines = [",".join(cols)]
    for row in result.history:  # a parameter a row's fit did not have (γ in implicit Euler) is empty
        lines.append(",".join("" if c not in row else f"{row[c]:.9g}" if isinstance(row[c], float) else str(row[c])
                              for c in cols))
    write_text_atomic(out / "fit_log.csv", "\n".join(lines) + "\n")
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
    with atomic_path(out / "fit.png") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
