"""Implicit cloth stepping in the C-IPC formulation (Newton on the incremental potential).

One step minimises

    E(x) = ½‖x − x̃‖²_M / h² − Mg·x + Ψ_membrane(x) + Ψ_bending(x) + κ B(x) + h D(v(x))
           (+ damping),       x̃ = xₜ + h vₜ,

over the free cloth vertices; Dirichlet vertices sit at their prescribed targets and the body
at its pose at t+1. Newton with per-element PSD-projected Hessians, sparse Cholesky, and a
backtracking line search that starts from ipctk's collision-free step size (AdditiveCCD).

:meth:`ClothSim.step` is made of named parts: ``_begin_step`` (the step's state, handed to
every term's ``begin_step``), ``_start`` (the prescribed motion; start.py), then Newton
iterations of ``_newton_direction``, ``_line_search``, the barrier stiffness's update (kappa.py) and, while
the body is not at its pose, ``lag.penalty_phase``; ``_finish_step`` reports and keeps the
linearization that sensitivity.py differentiates.

Moving body (docs/simulation.md "Moving collider"): the prescribed motion (body t → t+1,
Dirichlet vertices → targets) is swept with CCD against the cloth at xₜ; if it is collision-
free it is applied and those DOFs eliminated. Otherwise the cloth is carried with the body
(start.follow_body) or, when that is cut too, the prescribed vertices become unknowns pulled
to their targets by a stiff penalty (KinematicPenalty) until they are snapped (IPC's Dirichlet
treatment).
"""

from __future__ import annotations

import dataclasses
import time

import ipctk
import numpy as np

from .assembly import Assembler, Linearization, NewtonLinearSolver
from .contact import Barrier, Friction, KinematicPenalty
from .crease import outer_surface
from .energies import Bending, Gravity, Inertia, MassDamping, Membrane, StiffnessDamping
from .kappa import adapt_stiffness, initial_stiffness
from .lag import confine_lag, penalty_phase
from .material import Material
from .mesh import ClothTopology
from .pipeline import PipelinedLinearSolver
from .settings import SimSettings, StepStats
from .linesearch import CandidateScene, EnergyMemo, backtrack, expand_step
from .start import follow_body, release_weight, warm_start
from .terms import StepState
from .untangle import PINCH_DISTANCE, untangle_start

CUT_FORCING = 10.0  # newton_forcing × this after a CCD-cut step (docs/simulation.md "Session 14")


@dataclasses.dataclass
class _Solve:
    """The running state of one step's Newton solve (ClothSim.step)."""

    X: np.ndarray  # the iterate [N + Nb, 3]
    penalty: bool  # the prescribed vertices are unknowns (kinematic-penalty phase)
    X_goal: np.ndarray  # the prescribed positions at t+1
    diag: float  # bounding-box diagonal (ipctk's κ update)
    lag_left: int  # friction re-lags still allowed (SimSettings.friction_iterations)
    prev_min_dist: float
    prev_residual: float = np.inf
    below_count: int = 0  # consecutive directions below newton_tol ("rms")
    penalty_iters: int = 0
    gaps: list = dataclasses.field(default_factory=list)  # the penalty phase's gap per iteration
    cut: bool = False  # the last step was cut by CCD (α < 1): the next direction may be looser
    first: bool = True  # no step taken yet in this step's solve
    confined: bool = False  # a given-up penalty phase left only the body near the pinch behind (lag.py)
    lag_stall: bool = False  # the body lags (confined): the free solve ends once it stalls (ClothSim.lag_stall_exit)
    lows: list = dataclasses.field(default_factory=list)  # (while lag_stall) the stopping norm per iteration
    floors: int = 0  # consecutive line searches that ended at their floor (α < 1e-12: no progress)
    matrix: object = None  # the last Newton matrix
    linear_solver: NewtonLinearSolver | None = None  # the solver of the last Newton system
    memo: EnergyMemo = dataclasses.field(default_factory=EnergyMemo)  # E at the last iterate


class ClothSim:
    """Implicit-Euler / BDF2 C-IPC cloth simulator for one garment against one moving body.

    Args:
        rest_vertices: [N, 3] garment rest positions (its stress-free shape).
        faces: [F, 3] consistently oriented triangles.
        material: :class:`Material`.
        settings: :class:`SimSettings`.
        boundary_indices: [K] Dirichlet vertices (follow prescribed targets every step).
        extra_terms: further terms of E (the protocol of terms.py), added after the built-in
            ones; they see the stacked positions [cloth; body] like every term.
        contact_exclude: [P, 2] cloth vertex pairs left out of self-contact (ContactScene's ``exclude``).
    """

    predict_acceleration = True  # implicit Euler: Newton starts at x̃ + h² aₜ (last step's aₜ)
    stall_exit, stall_window, stall_progress = False, 8, 0.1  # give up a penalty phase: gap -10 % in 8 (simulate)
    crease_on = False  # cloth collides with the body's outer surface only (crease.py; simulate: on a lag's retry)
    crease_visible = False  # ... and with the visible part of the triangles next to a crease (crease.VisibleContact)
    lag_stall_exit = False  # a lagging step's free solve ends once it stalls (simulate turns it on; _Solve.lag_stall)
    floor_exit = 0  # >0: the Newton solve ends after this many line searches in a row at their floor (sim.rest)
    _crease_check = False  # the last step hid body or released cloth: look for cloth inside the body (crease.py)

    def __init__(self, rest_vertices, faces, material: Material, settings: SimSettings = SimSettings(),
                 boundary_indices=(), extra_terms=(), contact_exclude=None):
        if settings.newton_norm not in ("rms", "max") or settings.newton_window < 1:
            raise ValueError(f"newton_norm {settings.newton_norm!r} / newton_window {settings.newton_window}: "
                             "expected 'rms' or 'max' and a window >= 1")
        if settings.integrator not in ("euler", "bdf2"):
            raise ValueError(f"integrator {settings.integrator!r}: expected 'euler' or 'bdf2'")
        self.settings = settings
        # the step of the implicit solve: h (implicit Euler, and BDF2's first step) or 2h/3 (BDF2)
        self.h_implicit = settings.dt
        self._last_step = None  # (x_new, v_new, x, v) of the last step: BDF2's history
        self._body_lag = None  # (pose the last step was given, pose it reached) when it fell short
        self.material = material
        self.topo = ClothTopology.build(rest_vertices, faces)
        self.n = len(self.topo.rest)
        self.boundary = np.unique(np.asarray(boundary_indices, dtype=np.int64))
        self.extra_terms, self.contact_exclude = list(extra_terms), contact_exclude
        self.scene = None
        self.barrier_stiffness = 0.0
        self.max_barrier_stiffness = 0.0
        self._kappa_balanced = False
        self.linearization = None
        self.step_state: StepState | None = None  # the last step's state (StepState)
        self._body_faces = None
        solver_kw = dict(backend=settings.linear_solver, preconditioner=settings.preconditioner,
                         threads=settings.solver_threads)
        # the preconditioner factorised on a second thread, one iteration behind (pipeline.py);
        # not with keep_linearization (the sensitivities read the step's last factor)
        free_solver = (PipelinedLinearSolver if settings.factor_thread and not settings.keep_linearization
                       else NewtonLinearSolver)
        self.linear_solver = free_solver(settings.linear_rtol, settings.max_cg_iterations, **solver_kw)
        # The penalty-mode system (body DOFs unknown too) keeps its own preconditioner, so
        # switching between the two systems within a step costs no refactorisation. Its path
        # decides where the body is snapped and friction re-lagged, so it is solved to 1e-10
        # (as exact as a direct solve: the ρ-scaling invariance test holds to 1e-5 only then).
        self.linear_solver_all = NewtonLinearSolver(1e-10, settings.max_cg_iterations, **solver_kw)

    @property
    def dmin(self) -> float:
        """The contact thickness [m] (:meth:`SimSettings.contact_thickness`)."""
        return self.settings.contact_thickness(self.material)

    # -- setup ---------------------------------------------------------------------------------

    def prepare(self, collider_vertices, collider_faces):
        """Build the terms and the contact scene for this body (None: no body); ``step`` does it
        when the body changes; call it to inspect :meth:`active_terms` before the first step."""
        if collider_vertices is None:  # no body: an empty collider
            collider_vertices, collider_faces = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
        bt = np.asarray(collider_vertices, dtype=np.float64).reshape(-1, 3)
        if (self.scene is None or len(bt) != self.nb
                or not np.array_equal(np.asarray(collider_faces).reshape(-1, 3), self._body_faces)):
            self._setup(bt, collider_faces)

    def _setup(self, body_vertices, body_faces):
        s, m = self.settings, self.material
        body_faces = np.asarray(body_faces, dtype=np.int64).reshape(-1, 3)
        self._body_faces = body_faces
        self.nb = len(body_vertices)
        self.linear_solver.reset()  # a different system: its factor is no preconditioner
        self.linear_solver_all.reset()
        n_total = self.n + self.nb
        self.scene = CandidateScene(self.topo.rest, self.topo.faces, body_vertices, body_faces, s.dhat, self.dmin,
                                  s.self_contact, exclude=self.contact_exclude, prescribed=self.boundary)
        self.scene.ccd_threads = s.ccd_threads if s.deterministic else 0
        self.scene.build_threads = s.candidate_threads if s.deterministic else 0
        self.scene.canonical = s.candidate_threads > 0  # (0: the candidates' own order, one thread)
        free = np.ones(n_total)
        free[self.boundary] = 0.0
        free[self.n:] = 0.0
        topo = dataclasses.replace(  # pad per-vertex rest data to the stacked [cloth; body] rows
            self.topo, vertex_area=np.r_[self.topo.vertex_area, np.zeros(self.nb)],
            rest=np.vstack([self.topo.rest, body_vertices]),
        )
        self.inertia = Inertia(topo, m.density, self.h_implicit, free)
        self.gravity = Gravity(topo, m.density, free, np.asarray(s.gravity, dtype=np.float64))
        self.membrane = Membrane(self.topo, m.stretch_stiffness, m.poisson, s.membrane_model)
        self.bending = Bending(self.topo, m.bend_stiffness)
        self.bending.projection = s.bending_hessian
        self.barrier = Barrier(self.scene, max(self.barrier_stiffness, 1e-300))
        self.friction = Friction(self.scene, s.friction, s.friction_eps_v, self.h_implicit)
        self.terms = [self.inertia, self.gravity, self.membrane, self.bending]
        if s.damping_mass > 0:
            self.terms.append(MassDamping(self.inertia, s.damping_mass))
        if s.damping_stiffness > 0:
            self.terms.append(StiffnessDamping(s.damping_stiffness, self.h_implicit, [self.membrane, self.bending]))
        self.terms += self.extra_terms
        self._mean_mass = m.density * float(np.mean(self.topo.vertex_area))
        kinematic = np.r_[self.boundary, np.arange(self.n, n_total)]
        self.penalty = KinematicPenalty(kinematic, s.kinematic_penalty * self._mean_mass, n_total, self.h_implicit)
        # Two reduced systems: free cloth DOFs only, and everything (penalty mode).
        dof_free = np.full(3 * n_total, -1, dtype=np.int64)
        free_dofs = (3 * np.flatnonzero(free)[:, None] + np.arange(3)).ravel()
        dof_free[free_dofs] = np.arange(len(free_dofs))
        elements = [self.topo.faces, self.topo.hinges]
        # hinge tips (x2, x3) are not (usually) joined by an edge: only bending couples them,
        # and the CG preconditioner drops that coupling (assembly.NewtonLinearSolver)
        tips = self.topo.hinges[:, 2:]
        self.assembler_free = Assembler(dof_free, elements, tips)
        self.assembler_all = Assembler(np.arange(3 * n_total), elements, tips)
        # ipctk's adaptive κ expects the mass of an energy ½‖x − x̃‖²_M + h²Ψ; ours is that
        # divided by h², so the matching "average mass" is m̄ / h² (κ then scales with ρ).
        self._average_mass = self._mean_mass / self.h_implicit**2
        self._n_free = max(1, self.n - len(self.boundary))

    def reset(self):
        """Forget the adaptive barrier stiffness (it persists across steps, as in IPC)."""
        self.barrier_stiffness = 0.0
        self.max_barrier_stiffness = 0.0
        self._kappa_balanced = False

    def set_dt(self, dt: float):
        """Step length of the following steps (simulate's per-frame substeps). BDF2's history
        assumes equal steps: a new length restarts it with an implicit-Euler step."""
        if dt != self.settings.dt:
            self.settings = dataclasses.replace(self.settings, dt=float(dt))
            self._last_step = None

    def get_state(self) -> dict:
        """What the next step depends on besides (x, v) and the settings: the adaptive barrier
        stiffness (persists across steps, as in IPC), BDF2's history, where a lagging body
        stopped. Arrays and floats (an .npz holds it); :meth:`set_state` restores it, after
        which the next step is bit-identical to the one the captured sim would take."""
        out = {"dt": self.settings.dt, "barrier_stiffness": self.barrier_stiffness,
               "max_barrier_stiffness": self.max_barrier_stiffness, "kappa_balanced": self._kappa_balanced,
               "crease_check": self._crease_check}
        if self._last_step is not None:
            out["last_step"] = np.stack(self._last_step)
        if self._body_lag is not None:
            out["body_lag"] = np.stack(self._body_lag)
        return out

    def set_state(self, state: dict):
        """Restore :meth:`get_state`'s dict (this sim's or one saved from an equal sim)."""
        self.set_dt(float(state["dt"]))
        self.barrier_stiffness = float(state["barrier_stiffness"])
        self.max_barrier_stiffness = float(state["max_barrier_stiffness"])
        self._kappa_balanced = bool(state["kappa_balanced"])
        self._crease_check = bool(state.get("crease_check", False))
        if self.scene is not None:
            self.barrier.set_stiffness(max(self.barrier_stiffness, 1e-300))
        last, lag = state.get("last_step"), state.get("body_lag")
        self._last_step = None if last is None else tuple(np.array(a, dtype=np.float64) for a in last)
        self._body_lag = None if lag is None else tuple(np.array(a, dtype=np.float64) for a in lag)

    # -- energy --------------------------------------------------------------------------------

    def active_terms(self, penalty: bool = False) -> list:
        """The terms of E: elastic and inertial ones, barrier, friction (and the kinematic
        penalty while the prescribed vertices are unknowns)."""
        terms = self.terms + [self.barrier, self.friction]
        return terms + [self.penalty] if penalty else terms

    def _energy(self, X, penalty):
        total = 0.0
        for t in self.active_terms(penalty):
            total += t.energy(X)
            if not np.isfinite(total):
                return np.inf
        return total

    def exact_hessian(self, X):
        """(H, dof_map): the exact (unprojected) ∇²E at X over the free DOFs (CSR) and the DOF
        map (reduced row of each DOF, -1 = prescribed). The one the last step kept
        (SimSettings.keep_linearization) when X is its solution, else assembled here."""
        lin = self.linearization
        if lin is not None and lin.hessian is not None and np.array_equal(X, lin.positions):
            return lin.hessian, lin.dof_map
        self.scene.prepare_static(X)
        H = self.assembler_free.assemble([t.hessian(X, project=False) for t in self.active_terms()])
        return H, self.assembler_free.dof_map

    # -- one step ------------------------------------------------------------------------------

    def step(self, x, v, collider_vertices_t, collider_vertices_t1, collider_faces,
             boundary_targets=None, history=None):
        """Advance one implicit step of length settings.dt (implicit Euler or BDF2).

        Args:
            x: [N, 3] cloth positions at t (intersection-free with the body at t).
            v: [N, 3] cloth velocities at t.
            collider_vertices_t: [Nb, 3] body at t; collider_vertices_t1: [Nb, 3] body at t+1
                (None for both: no collider).
            collider_faces: [Fb, 3] body triangles (same for every step of a sim).
            boundary_targets: [K, 3] Dirichlet vertex positions at t+1 (order of the sorted
                ``boundary_indices``); None keeps them where they are.
            history: (x [N, 3], v [N, 3]) at t−1, used by BDF2 only. None: the last step's
                input when this step continues it (x, v are its output), else none (an
                implicit-Euler step). :meth:`step_base` gives the resulting x̂, v̂, ĥ.

        Returns:
            (x_new [N, 3], v_new [N, 3], StepStats).
        """
        t_start = time.perf_counter()
        # one ipctk thread: its threaded sums' order depends on scheduling (DESIGN.md: same inputs, same outputs)
        if self.settings.deterministic:
            ipctk.set_num_threads(1)
        stats = StepStats()
        x = np.asarray(x, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        # after a pinch: cloth left inside or through the body moved out first (untangle.py)
        x, stats.untangled_vertices = untangle_start(self, x, collider_vertices_t, collider_faces)
        state, x_pred = self._begin_step(x, v, collider_vertices_t, collider_vertices_t1, collider_faces,
                                         boundary_targets, history, stats)
        free = self.inertia.unit_mass[: self.n] > 0  # the body's own creases (crease.py)
        stats.buried_vertices, stats.released_vertices = outer_surface(self, state.x_prev, state.x_goal, free)
        solve = self._start(state, x, x_pred, stats)
        self._newton(solve, stats)
        # (not in an attempt that simulate retries in shorter steps if it lags: stall_exit)
        if (solve.penalty and self.settings.lag_radius > 0 and self.nb and not self.stall_exit
                and confine_lag(self, solve, stats)):
            done = (stats.newton_iterations, stats.factorizations, stats.cg_iterations)
            # the step lags (reported): solved until the norm stalls (docs/simulation.md "Session 21")
            kin = self.penalty.kinematic
            solve.lag_stall = self.lag_stall_exit and bool(np.any(solve.X[kin] != self.penalty.target))
            self._newton(solve, stats)  # the rest of the step with the body where confine_lag left it
            stats.newton_iterations += done[0]
            stats.factorizations += done[1]
            stats.cg_iterations += done[2]
        x_new, v_new = self._finish_step(solve, state, stats)
        self._last_step = (x_new, v_new, x.copy(), v.copy())
        stats.time["total"] = time.perf_counter() - t_start
        return x_new, v_new, stats

    def _begin_step(self, x, v, body_t, body_t1, body_faces, boundary_targets, history, stats):
        """The step's :class:`StepState` (x̂, v̂, ĥ from step_base; the body at the matching
        constant-velocity base), handed to every term's ``begin_step``, and the inertial
        prediction x̃ = x̂ + ĥ v̂ [N, 3]."""
        h = self.settings.dt
        self.prepare(body_t, body_faces)
        if body_t is None:
            body_t = body_t1 = np.zeros((0, 3))
        bt = np.asarray(body_t, dtype=np.float64).reshape(-1, 3)
        bt1 = np.asarray(body_t1, dtype=np.float64).reshape(-1, 3)
        lag, self._body_lag = self._body_lag, None
        if lag is not None and np.array_equal(lag[0], bt):
            bt = lag[1]  # the last step's body stopped short of this pose: go on from where it is
            stats.body_lagged = True
        X_prev = np.vstack([x, bt])
        base, vbase, hh = self.step_base(x, v, history)
        self.h_implicit = hh
        self._average_mass = self._mean_mass / hh**2
        X_goal = X_prev.copy()
        X_goal[self.n:] = bt1
        if len(self.boundary) and boundary_targets is not None:
            X_goal[self.boundary] = np.asarray(boundary_targets, dtype=np.float64)
        state = StepState(
            x_prev=X_prev, x_base=np.vstack([base, bt + (1.0 - hh / h) * (bt1 - bt)]),
            v_base=np.vstack([vbase, (bt1 - bt) / h]), x_goal=X_goal, h=hh, dt=h,
        )
        for t in self.active_terms(penalty=True):
            t.begin_step(state)
        self.step_state = state
        x_pred = base + hh * vbase
        last = self._last_step
        if (self.predict_acceleration and self.settings.integrator == "euler" and last is not None
                and np.array_equal(last[0], x) and np.array_equal(last[1], v)):
            # the Newton start also extrapolates the last step's acceleration (only the start:
            # x̃ of the inertia term is unchanged)
            x_pred = x_pred + (hh * hh / h) * (v - last[3])
        return state, x_pred

    def _start(self, state, x, x_pred, stats) -> _Solve:
        """Where Newton starts, and in which mode: the prescribed move swept with CCD; if it is
        free, the prescribed DOFs are eliminated at their targets (and the cloth starts from
        the inertial prediction when that lowers E, start.warm_start); if not, the cloth is
        carried with the body (start.follow_body) or the penalty phase starts."""
        s = self.settings
        X_prev, X_goal = state.x_prev, state.x_goal
        tc = time.perf_counter()
        alpha = self.scene.collision_free_stepsize(X_prev, X_goal)
        stats.time["ccd"] += time.perf_counter() - tc
        penalty = alpha < 1.0
        X = X_prev.copy() if penalty else X_goal.copy()
        free = self.inertia.unit_mass[: self.n] > 0
        if penalty and s.follow_body > 0 and self.nb:
            info = {}
            X, reached = follow_body(self.scene, self._body_faces, free, s, X_prev, X_goal, x_pred, stats, info=info)
            penalty = not reached
            stats.body_follows += int(reached)
            if reached and s.follow_release > 0:  # the carried cloth off the body back toward x̃ (Session 23)
                w = release_weight(info["distance"], s.dhat, s.follow_release)
                X = warm_start(self.scene, self.terms + [self.barrier], free, X, x_pred, stats, weight=w)
        elif not penalty and s.warm_start and np.any(x_pred != x):
            # friction is not lagged yet at this point
            X = warm_start(self.scene, self.terms + [self.barrier], free, X, x_pred, stats)
        diag = self.scene.bbox_diagonal(X_goal)
        self.scene.prepare_static(X)
        initial_stiffness(self, X)
        self.friction.lag(X, self.barrier)
        return _Solve(X=X, penalty=penalty, X_goal=X_goal, diag=diag,
                      lag_left=max(1, s.friction_iterations) - 1, prev_min_dist=self.scene.min_distance(X))

    def _newton(self, sv: _Solve, stats):
        """Newton iterations until the stopping rule (SimSettings.newton_norm) holds."""
        s = self.settings
        solvers = (self.linear_solver, self.linear_solver_all)
        for ls in solvers:  # the last step's factors no longer fit (body, x̃, contacts moved);
            # only the sensitivities (keep_linearization) read the last step's factors afterwards
            ls.mark_stale(keep=s.keep_linearization)
        sv.linear_solver = self.linear_solver
        n_fact0 = sum(ls.factorizations for ls in solvers)
        n_cg0 = sum(ls.cg_iterations for ls in solvers)
        for it in range(s.max_newton_iterations):
            stats.newton_iterations = it + 1
            step, residual, res_stop = self._newton_direction(sv, stats)
            stats.residual = res_stop
            below = not sv.penalty and res_stop < s.newton_tol
            if s.newton_norm == "max" and below:  # the step is not taken: it is below tolerance
                if self._relag_friction(sv):
                    continue
                stats.converged = True
                break
            # "rms" (Codim-IPC): the step is taken; stop once the last newton_window directions were below tol
            sv.below_count = sv.below_count + 1 if below else 0
            stop_after_step = s.newton_norm == "rms" and sv.below_count >= s.newton_window
            self._line_search(sv, step, residual, stats)
            if self.floor_exit and sv.floors >= self.floor_exit:
                break  # the iterate no longer moves (energy changes below round-off): not converged
            adapt_stiffness(self, sv, stats)
            sv.lows += [res_stop] if sv.lag_stall else []  # no new low in stall_window iterations: done
            w = self.stall_window
            if sv.lag_stall and len(sv.lows) > w and min(sv.lows[-w:]) >= min(sv.lows[:-w]):
                break
            if sv.penalty:
                action = penalty_phase(self, sv, stats)
                if action == "break":
                    break
                if action == "continue":
                    continue
            # The last CCD segment's candidates (inflated by d̂) hold every pair within d̂ of
            # any point on it, X_new included: no rebuild for the next iteration's barrier set.
            if not self.scene.covers_last_point:
                self.scene.prepare_static(sv.X)
            if stop_after_step:
                if self._relag_friction(sv):
                    sv.below_count = 0
                    continue
                stats.converged = True
                break
        stats.penalty_iterations = sv.penalty_iters
        stats.factorizations = sum(ls.factorizations for ls in solvers) - n_fact0
        stats.cg_iterations = sum(ls.cg_iterations for ls in solvers) - n_cg0

    def _relag_friction(self, sv: _Solve) -> bool:
        """Re-lag friction at the iterate if SimSettings.friction_iterations allows another."""
        if sv.lag_left <= 0:
            return False
        self.friction.lag(sv.X, self.barrier)
        sv.lag_left -= 1
        return True

    def _newton_direction(self, sv: _Solve, stats):
        """The projected Newton step at the iterate: (step [N + Nb, 3], ‖Δx‖∞ / h, the stopping
        norm). Gradient and PSD-projected Hessian of every active term, assembled over the
        unknown DOFs and solved by preconditioned CG (NewtonLinearSolver); a direction that
        would end the solve is refined to 1e-10 first."""
        s = self.settings
        h = s.dt
        penalty = sv.penalty
        assembler = self.assembler_all if penalty else self.assembler_free
        initial_stiffness(self, sv.X)
        ta = time.perf_counter()
        grads_el, hess_el, grads_c, hess_c = [], [], [], []
        # the contact preview (SimSettings.contact_preview) on a step's first direction and after a CCD-cut one
        preview = s.contact_preview > 0 and not penalty and (sv.first or sv.cut)
        for t in self.active_terms(penalty):
            contact = t is self.barrier or t is self.friction
            tt = time.perf_counter()
            g = t.gradient(sv.X)
            if preview and t is self.barrier:  # in the matrix only: E, ∇E and the line search keep d̂
                H = t.preview_hessian(sv.X, s.contact_preview * s.dhat)
            else:
                H = t.hessian(sv.X, project=True)
            if contact:
                grads_c.append(g)
                hess_c.append(H)
                stats.time["contact"] += time.perf_counter() - tt
            else:
                grads_el.append(g)
                hess_el.append(H)
        grad = assembler.reduce(np.sum(grads_el + grads_c, axis=0))
        Hm = assembler.assemble(hess_el + hess_c)
        stats.time["assembly"] += time.perf_counter() - ta
        tl = time.perf_counter()
        # penalty iterations: their (larger) system by CG too, to 1e-10 (linear_solver_all);
        # free ones inexact: a loose direction while far from the solution (the stopping step is
        # refined to 1e-10 below); 10× looser after a CCD-cut step (this one will likely be cut too)
        sv.linear_solver = self.linear_solver_all if penalty else self.linear_solver
        loose = sv.cut and s.integrator == "euler"  # BDF2: docs/simulation.md "Session 14"
        forcing = None if penalty else s.newton_forcing * (CUT_FORCING if loose else 1.0)
        dx = -sv.linear_solver.solve(Hm, grad, assembler, forcing)
        sv.matrix = Hm
        stats.time["linear_solve"] += time.perf_counter() - tl
        step = assembler.expand(dx).reshape(-1, 3)
        residual, res_stop = self._residuals(step, h)
        if not penalty and res_stop < s.newton_tol:  # about to stop: make dx exact first
            tl = time.perf_counter()
            if preview:  # the stopping test is on the Newton matrix itself: the barrier's own Hessian
                hess_c[0] = self.barrier.hessian(sv.X, project=True)
                Hm = sv.matrix = assembler.assemble(hess_el + hess_c)
            dx = -self.linear_solver.refine(Hm, grad, -dx, assembler)
            stats.time["linear_solve"] += time.perf_counter() - tl
            step = assembler.expand(dx).reshape(-1, 3)
            residual, res_stop = self._residuals(step, h)
        return step, residual, res_stop

    def _line_search(self, sv: _Solve, step, residual, stats):
        """Backtracking from the collision-free step size (CCD) until E does not increase; a
        full step on a linearly converging tail is also tried longer (expand_step)."""
        E0 = sv.memo.get(EnergyMemo.key(self, sv.X, sv.penalty))
        X_new, E1, alpha = backtrack(self.scene, lambda Y: self._energy(Y, sv.penalty), sv.X, step, stats, E0)
        sv.memo.set(EnergyMemo.key(self, X_new, sv.penalty), E1)
        sv.cut = alpha < 1.0
        sv.first = False
        sv.floors = sv.floors + 1 if alpha < 1e-12 else 0
        if (self.settings.step_expansion and not sv.penalty and alpha == 1.0
                and residual > 0.7 * sv.prev_residual):
            tls = time.perf_counter()
            X_new = expand_step(self.scene, lambda Y: self._energy(Y, False), sv.X, step, X_new, E1, stats)
            stats.time["line_search"] += time.perf_counter() - tls
        sv.prev_residual = residual
        sv.X = X_new

    def _finish_step(self, sv: _Solve, state: StepState, stats):
        """Report the step, keep its linearization (sensitivities), and return (x_new, v_new)."""
        s = self.settings
        X = sv.X
        if sv.penalty or sv.confined:  # never reached the targets (or only away from a pinch, lag.py):
            # report, keep the best state, let the body lag
            stats.converged = stats.converged and not sv.penalty
            gap = np.linalg.norm(X[self.penalty.kinematic] - self.penalty.target, axis=1)
            stats.body_gap, stats.lag_vertices = float(np.max(gap)), int(np.count_nonzero(gap))
            self._body_lag = (state.x_goal[self.n:].copy(), X[self.n:].copy())
        stats.barrier_stiffness = self.barrier_stiffness
        # the last build usually holds X (the next step starts with its own CCD build, so only
        # the reported contacts, the same set, come from these candidates)
        if s.keep_linearization or not self.scene.covers(X):
            self.scene.prepare_static(X)
        c = self.scene.collisions_at(X)
        stats.n_contacts = len(c)
        stats.min_distance = float(np.sqrt(self.scene.min_distance(X)))  # ipctk: squared
        if sv.penalty or sv.confined or stats.body_lagged or stats.min_distance < PINCH_DISTANCE:
            # a pinch (the body lags, or a pair nm apart, where AdditiveCCD can step through it):
            # look for cloth inside or through the body at the next step's start (untangle.py)
            self._crease_check = True
        ls = sv.linear_solver
        self.linearization = Linearization(
            (self.assembler_all if sv.penalty else self.assembler_free).dof_map, sv.matrix,
            factorization=(ls.factor if ls.factor_matrix is sv.matrix else None),
            positions=X, preconditioner=self.linear_solver.factor,
        )
        if s.keep_linearization and not sv.penalty:
            hess = [t.hessian(X, project=False) for t in self.active_terms()]
            self.linearization.hessian = self.assembler_free.assemble(hess)
        x_new = X[: self.n].copy()
        v_new = (x_new - state.x_base[: self.n]) / state.h
        return x_new, v_new

    # -- integrator and helpers ----------------------------------------------------------------

    def step_base(self, x, v, history=None):
        """(x̂, v̂, ĥ) of a step from (x, v): the inertial prediction is x̂ + ĥ v̂ and the step's
        velocity (x⁺ − x̂) / ĥ. Implicit Euler: (x, v, h). BDF2: (4/3 x − 1/3 xₚ,
        4/3 v − 1/3 vₚ, 2h/3) with (xₚ, vₚ) = ``history``, or the last step's input when (x, v)
        is its output; with neither, an implicit-Euler step (x, v, h). The material's
        ``bdf2_blend`` γ < 1 weighs the history less: ((1 + γ/3) x − γ/3 xₚ, likewise v,
        (1 − γ/3) h), a first-order blend between implicit Euler (γ = 0) and BDF2 (γ = 1)."""
        h = self.settings.dt
        if self.settings.integrator != "bdf2":
            return x, v, h
        if history is None:
            last = self._last_step
            if last is None or not (np.array_equal(last[0], x) and np.array_equal(last[1], v)):
                return x, v, h
            history = last[2:]
        xp, vp = (np.asarray(a, dtype=np.float64) for a in history)
        g = self.material.bdf2_blend / 3.0  # γ/3: 1/3 is BDF2, 0 implicit Euler (Material.bdf2_blend)
        return (1.0 + g) * x - g * xp, (1.0 + g) * v - g * vp, (1.0 - g) * h

    def _residuals(self, step, h):
        """(‖Δx‖∞ / h, the stopping norm of SimSettings.newton_norm) over the cloth vertices.

        "rms" is Codim-IPC's (the official PhysAvatar setup): sqrt(Σ_i ‖Δx_i‖² / n_free) / h
        over the free cloth vertices (prescribed ones have Δx_i = 0 outside penalty mode).
        """
        cloth = step[: self.n]
        if not cloth.size:
            return 0.0, 0.0
        res_max = float(np.max(np.abs(cloth))) / h
        if self.settings.newton_norm == "max":
            return res_max, res_max
        return res_max, float(np.sqrt(np.sum(cloth * cloth) / self._n_free)) / h
