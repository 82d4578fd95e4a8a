"""Settings of the cloth simulator and what one step reports (SimSettings, StepStats)."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class SimSettings:
    """Solver settings (SI units). Defaults: the official PhysAvatar Codim-IPC setup.

    Attributes:
        dt: time step [s] (0.04 = one step per frame at 25 fps).
        integrator: "euler" (implicit Euler, the paper's and Codim-IPC's) or "bdf2" (the
            two-step backward differentiation formula, IPC's other integrator: second order, so
            far less numerical damping at the same step; docs/simulation.md "Time integration").
            BDF2 is implicit Euler with step 2h/3 from x̂ = 4/3 xₜ − 1/3 xₜ₋₁ with velocity
            4/3 vₜ − 1/3 vₜ₋₁; the previous state comes from ``step(history=...)`` or, when the
            step continues the last one, from the sim itself; without one (the first step) the
            step is implicit Euler (a second-order start: the velocity error is O(h²)).
        dhat: barrier activation distance d̂ [m].
        dmin: minimum separation kept between cloth and body [m] (a thickness: ipctk's d_min,
            the barrier acting on d² − d_min² within (2 d_min + d̂) d̂); 0 = the material's
            ``contact_offset`` (ClothSim.dmin; sim.offset estimates it from a template).
        friction: Coulomb coefficient μ (0 turns friction off).
        friction_eps_v: velocity below which friction is static [m/s] (ipctk ε_v).
        friction_iterations: lagged-friction updates per step (1 = λ, T from the step start).
        self_contact: resolve garment–garment contact too.
        membrane_model: "stvk" (the paper) or "neohookean" (Codim-IPC default).
        damping_mass: Rayleigh α [1/s], damping force −α M v.
        damping_stiffness: Rayleigh β [s], damping force −β K(xₜ) v.
        newton_tol: stop when the Newton step Δx, as a velocity Δx / h, is below newton_tol
            [m/s] in the norm ``newton_norm``.
        newton_norm: "rms" (default; Codim-IPC's, the official PhysAvatar setup): the root
            mean square over the free cloth vertices of ‖Δx_i‖ / h, the step is taken, and the
            solve ends once ``newton_window`` consecutive steps were below newton_tol (Codim-IPC
            uses 3; 1 here: docs/simulation.md "Speed" compares them). "max": ‖Δx‖∞ / h
            (no vertex's implicit velocity changes by more than newton_tol), the step is not
            taken (stricter).
        newton_window: see newton_norm ("rms" only).
        bending_hessian: PSD approximation of the hinge Hessians in the Newton matrix:
            "gauss_newton" (c ∇θ∇θᵀ, PSD by construction, no eigendecomposition; the cloth-
            solver standard) or "eigen" (exact Hessian with eigenvalues clamped at 0). Only the
            search direction depends on it, not the solution.
        warm_start: start Newton from the CCD-clipped inertial prediction xₜ + h vₜ when its
            energy is lower than at xₜ (else from xₜ).
        follow_body: when the body's move to its pose at t+1 is cut by CCD (which would start
            the kinematic-penalty phase), first try a start where every free cloth vertex within
            this distance [m] of the body is carried rigidly with its closest body triangle
            (fading to the inertial prediction at twice the distance). If that move is
            collision-free, Newton starts there with the body at its pose and no penalty phase;
            otherwise the penalty phase starts from its collision-free part. 0 = off. Changes
            the path to the minimiser, not the minimiser.
        follow_release: r > 0 [m]: after a carry that reached the body's pose, the carried cloth
            moves back toward its inertial prediction, none of the way within 2 d̂ of the body
            (at the step's start), all of it from r on, linear between (start.release_weight);
            the move is CCD-clipped and kept when it lowers E (start.warm_start). The carry
            holds cloth up to follow_body from the body rigidly, ~8-10 mm from the step's
            solution where the prediction is ~3 mm from it (docs/simulation.md "Session 23").
            Changes the path to the minimiser, not the minimiser. 0 = off.
        step_expansion: when a full Newton step was accepted but the residual fell by less
            than 30%, also try 2, 4, ... 64 times the step (CCD- and energy-checked;
            sim.linesearch.expand_step). Changes the path to the minimiser, not the minimiser.
        linear_rtol, max_cg_iterations: the Newton system is solved by CG, preconditioned
            with the Cholesky factor of a sparsified (1-ring) Newton matrix, to relative
            residual linear_rtol; max_cg_iterations bounds CG before a fresh factor is taken
            (0 = factorise the Newton matrix itself every iteration, a direct solve).
        linear_solver: the sparse Cholesky behind the CG preconditioner and the direct solves:
            "auto" (MKL PARDISO for ≥ 3,000 unknowns when the optional ``mkl`` extra is
            installed, else cholespy),
            "pardiso" or "cholespy" (sim.assembly.Factorization; docs/simulation.md "Session
            21"). Both factor the same matrices exactly, so only rounding (the CG path) differs.
        preconditioner: the matrix whose factor preconditions CG: "sparsified" (the Newton
            matrix without the hinge-tip couplings, their magnitudes on the diagonal), "full"
            (the Newton matrix itself) or "auto" ("full" for ≥ 30k unknowns with PARDISO, where
            the sparsified factor needs ~50 CG iterations; assembly.NewtonLinearSolver).
        solver_threads: threads of PARDISO's factorisations and solves (1: bit-identical
            repeats; cholespy always runs on one).
        factor_thread: the CG preconditioner of the free system refactorised on a second
            thread for every Newton direction and used by the next one (sim.pipeline): its
            factorisations leave the main thread. Deterministic (the factor a solve uses depends
            on the iteration count only), but another CG path than the refresh rule's, so other
            bits than off. PARDISO factors only (cholespy's: the plain solver's bits); not with
            ``keep_linearization``. Slower on a 2-core machine with another job running
            (docs/simulation.md "Session 37"), hence off.
        newton_forcing: relative CG residual of the Newton directions that do not end the
            solve (inexact Newton; most are cut by CCD anyway). The direction that passes the
            stopping test is always refined to 1e-10, so only the path changes. Penalty-mode
            systems keep 1e-10 (their path decides where friction is re-lagged).
        max_newton_iterations: give up (and report converged=False) after this many.
        max_penalty_iterations: give up the kinematic-penalty phase after this many iterations
            (the body could not reach its pose: cloth pinched between body parts that leave it
            no room). The step keeps the intersection-free state it reached, and the body
            *lags*: the next step starts from where the body got to, not from the pose it was
            given (``StepStats.body_gap`` says how far short it stopped), so the state stays
            intersection-free and the body catches up once the pinch opens.
        barrier_stiffness_scale: ipctk min_barrier_stiffness_scale of the adaptive κ.
        kinematic_penalty: penalty weight of the prescribed vertices, × mean mass / h².
        keep_linearization: also assemble the exact (unprojected) Hessian at the solution and
            keep it with the last factorization in ``ClothSim.linearization`` (for adjoints).
            Without it the linearization's factors are valid until the next step, which
            refactorises them in place (PARDISO: no new symbolic analysis each step).
        deterministic: run ipctk single-threaded so results are bit-identical run to run.
        ccd_threads: threads of the CCD narrow phase (ipctk; with ``deterministic``). Its
            result is a minimum over the candidates, the same bits on any number of threads;
            1 by default: two were slower on a loaded 2-core machine, and process pools run
            one simulation per core (docs/simulation.md "Speed").
        candidate_threads: k ≥ 1: ipctk's candidate builds (the broad phase of every CCD and
            barrier set) on k threads (with ``deterministic``), and every barrier set sorted into a
            canonical order (contact.canonical_order): a threaded build lists its candidates in a
            schedule-dependent order, the sorted sets and their sums are the same bits for any k.
            0 (default): one thread, the sets in the candidates' own order (the bits of the
            code before session 32; no sorting, ~3 % of a demo frame). Two threads halve a build
            on an idle 2-core machine but lost on the shared one measured (docs/simulation.md
            "Session 32").
        contact_preview: r > 0: the Newton directions of a step's first iteration and of those
            after a CCD-cut step take, in their matrix, the Hessian of the barrier with d̂₂ = r d̂
            (r ≤ 2, pairs within d̂₂, the same κ) in place of the barrier's own (Barrier.
            preview_hessian): stiffer at every gap, and it sees pairs up to d̂₂, so fewer steps
            are cut by CCD. The energy and the stopping test are unchanged: it changes the path to
            the minimiser, not the minimiser (docs/simulation.md "Session 21"). 0 = off (the
            default: on, 1.25 cuts the demo walk's Newton iterations by 14 %, but moves the paths
            of the sensitivity checks' perturbed rollouts between nearby minima).
        max_body_move: with sub-stepping decided per frame (``simulate(max_substeps=...)``), a
            frame in which a body vertex within reach of the cloth moves farther than this [m]
            is split into ceil(move / max_body_move) implicit steps (sim.simulate.substep_count).
            0.08 m: the demo walk's body moves ≤ 6 cm a frame near the dress (one step per
            frame), the CMU hop's 0.2–0.3 m (3–4 steps).
        lag_radius: when a step's penalty phase gives up (max_penalty_iterations), only the
            prescribed vertices within this distance [m] of the pinch lag (fading out at twice
            the distance; doubled while the cloth cannot be carried along), the rest reach
            their pose (sim.lag.confine_lag); 0 = the whole body lags. Changes nothing in a step
            that does not give up.
        crease_ring: the cloth collides with the body's outer surface only: body vertices
            inside another part of the body at a step's start or end (its own creases, where
            Anny's collider passes through itself: groin, back of the knee), grown by this many
            rings, are left out of cloth–body contact for that step, and cloth vertices inside
            the body at its start are released (sim.crease.outer_surface). 1: every triangle
            with a buried corner goes; 0: only triangles with all corners buried; -1: off.
        uncollapse: a frame that lags where the body passes through itself within reach of the
            cloth is first retried on its end pose with the buried body vertices moved out onto
            the body's outer surface (sim.collapse; the crease rule follows if it still lags),
            and the frame after starts there (docs/simulation.md "Session 27").
        gravity: [3] m/s².
    """

    dt: float = 0.04
    integrator: str = "euler"
    dhat: float = 1e-3
    dmin: float = 0.0
    friction: float = 0.2
    friction_eps_v: float = 1e-3
    friction_iterations: int = 1
    self_contact: bool = False
    membrane_model: str = "stvk"
    damping_mass: float = 0.0
    damping_stiffness: float = 0.0
    newton_tol: float = 1e-3
    newton_norm: str = "rms"
    newton_window: int = 1
    bending_hessian: str = "gauss_newton"
    warm_start: bool = True
    follow_body: float = 0.04
    follow_segments: int = 4
    follow_lift: float = 1.0
    follow_retry: int = 3
    follow_release: float = 0.0
    step_expansion: bool = True
    linear_rtol: float = 1e-6
    newton_forcing: float = 1e-3
    max_cg_iterations: int = 100
    linear_solver: str = "auto"
    preconditioner: str = "auto"
    solver_threads: int = 1
    factor_thread: bool = False
    max_newton_iterations: int = 100
    max_penalty_iterations: int = 40
    barrier_stiffness_scale: float = 1e11
    kinematic_penalty: float = 1e6
    keep_linearization: bool = False
    deterministic: bool = True
    ccd_threads: int = 1
    candidate_threads: int = 0
    contact_preview: float = 0.0
    max_body_move: float = 0.08
    lag_radius: float = 0.05
    crease_ring: int = 1
    uncollapse: bool = True
    gravity: tuple = (0.0, 0.0, -9.81)

    def __post_init__(self):
        from .assembly import BACKENDS

        if self.linear_solver not in BACKENDS:
            raise ValueError(f"linear_solver {self.linear_solver!r}: expected one of {', '.join(BACKENDS)}")
        if not 0.0 <= self.contact_preview <= 2.0:
            raise ValueError(f"contact_preview {self.contact_preview}: expected 0 (off) or a ratio d̂₂/d̂ in (0, 2] "
                             "(the candidates hold the pairs within 2 d̂ only)")
        if self.candidate_threads < 0:
            raise ValueError(f"candidate_threads {self.candidate_threads}: expected 0 (the candidates' own order, "
                             "one thread) or a thread count k >= 1")

    def contact_thickness(self, material) -> float:
        """The contact thickness [m] (ipctk's d_min): ``dmin`` when set (> 0), else ``material``'s
        ``contact_offset`` (the model it was fitted in)."""
        return self.dmin if self.dmin > 0 else material.contact_offset

    def contact_room(self, material) -> float:
        """The room [m] the cloth's contact needs next to the body: d̂ + the contact thickness
        (what ``--knee-collapse`` auto compares a knee's crossing with, body.clearance.KNEE_ROOM)."""
        return self.dhat + self.contact_thickness(material)


@dataclasses.dataclass
class StepStats:
    """What one step did. Times in seconds."""

    newton_iterations: int = 0
    converged: bool = False
    line_search_iterations: int = 0
    step_expansions: int = 0  # line-search doublings beyond α = 1 (sim.linesearch.expand_step)
    penalty_iterations: int = 0
    body_follows: int = 0  # times the cloth was carried with the body (SimSettings.follow_body)
    body_gap: float = 0.0  # [m] how far the body (or a Dirichlet vertex) stopped short of its pose
    body_lagged: bool = False  # the step started from where the last step's body got to
    lag_vertices: int = 0  # prescribed vertices (body, attached cloth) short of their pose
    untangled_vertices: int = 0  # cloth vertices moved out of the body at the step's start (sim.untangle)
    lag_radius: float = 0.0  # [m] the lag was confined to this distance of the pinch (sim.lag); 0: not
    buried_vertices: int = 0  # body vertices inside another body part, left out of contact (sim.crease)
    released_vertices: int = 0  # cloth vertices inside the body at the start, released (sim.crease)
    barrier_stiffness: float = 0.0
    min_distance: float = float("inf")  # closest cloth–body (or cloth–cloth) distance [m]
    n_contacts: int = 0
    residual: float = float("inf")  # last ‖Δx‖∞ / h [m/s]
    factorizations: int = 0  # sparse Cholesky factorisations (the rest were CG solves)
    cg_iterations: int = 0
    time: dict = dataclasses.field(
        default_factory=lambda: dict(
            assembly=0.0, contact=0.0, linear_solve=0.0, ccd=0.0, line_search=0.0, total=0.0
        )
    )
