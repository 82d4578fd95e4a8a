"""Implicit-Euler cloth stepping in the C-IPC formulation (Newton on the incremental potential).

One step minimises

    E(x) = ½‖x − x̃‖²_M / h² − Mg·x + Ψ_membrane(x) + Ψ_bending(x) + κ B(x) + h D(v(x))
           (+ damping),       x̃ = xₜ + h vₜ,

over the free cloth vertices; Dirichlet vertices sit at their prescribed targets and the body
at its pose at t+1. Newton with per-element PSD-projected Hessians, sparse Cholesky, and a
backtracking line search that starts from ipctk's collision-free step size (AdditiveCCD).

Moving body (docs/simulation.md "Moving collider"): the prescribed motion (body t → t+1 and
Dirichlet vertices → targets) is first swept with CCD against the cloth at xₜ. If it is
collision-free it is applied at once and those DOFs are eliminated. Otherwise the prescribed
vertices become unknowns pulled to their targets by a stiff penalty (KinematicPenalty), so
every Newton step — body included — is limited by CCD and the barrier pushes the cloth ahead
of the body; once they are within tolerance of their targets and the last bit of motion is
collision-free, they are snapped and eliminated (IPC's Dirichlet treatment).
"""

from __future__ import annotations

import dataclasses
import time

import ipctk
import numpy as np

from .assembly import Assembler, Factorization, NewtonLinearSolver
from .contact import Barrier, ContactScene, Friction, KinematicPenalty
from .energies import Bending, Gravity, Inertia, MassDamping, Membrane, StiffnessDamping
from .material import Material
from .mesh import ClothTopology


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
        dmin: minimum separation kept between surfaces [m] (a thickness offset; 0 = none).
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
            uses 3; 1 here: docs/simulation.md "Session 6" measures both). "max": ‖Δx‖∞ / h
            (no vertex's implicit velocity changes by more than newton_tol), the step is not
            taken (the reference behaviour of earlier sessions; stricter).
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
        step_expansion: when a full Newton step was accepted but the residual fell by less
            than 30%, also try 2, 4, ... 64 times the step (CCD- and energy-checked;
            ClothSim._expand_step). Changes the path to the minimiser, not the minimiser.
        linear_rtol, max_cg_iterations: the Newton system is solved by CG, preconditioned
            with the Cholesky factor of a sparsified (1-ring) Newton matrix, to relative
            residual linear_rtol; max_cg_iterations bounds CG before a fresh factor is taken
            (0 = factorise the Newton matrix itself every iteration, a direct solve).
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
        deterministic: run ipctk single-threaded so results are bit-identical run to run.
        ccd_threads: threads of the CCD narrow phase (ipctk; with ``deterministic``). Its
            result is a minimum over the candidates, the same bits on any number of threads;
            1 by default: on the shared 2-core machine (load ≈ 4) two threads were slower
            (18 ms against 14 ms a call), and process pools run one simulation per core.
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
    step_expansion: bool = True
    linear_rtol: float = 1e-6
    newton_forcing: float = 1e-3
    max_cg_iterations: int = 100
    max_newton_iterations: int = 100
    max_penalty_iterations: int = 40
    barrier_stiffness_scale: float = 1e11
    kinematic_penalty: float = 1e6
    keep_linearization: bool = False
    deterministic: bool = True
    ccd_threads: int = 1
    gravity: tuple = (0.0, 0.0, -9.81)


@dataclasses.dataclass
class StepStats:
    """What one step did. Times in seconds."""

    newton_iterations: int = 0
    converged: bool = False
    line_search_iterations: int = 0
    step_expansions: int = 0  # line-search doublings beyond α = 1 (ClothSim._expand_step)
    penalty_iterations: int = 0
    body_follows: int = 0  # times the cloth was carried with the body (SimSettings.follow_body)
    body_gap: float = 0.0  # [m] how far the body (or a Dirichlet vertex) stopped short of its pose
    body_lagged: bool = False  # the step started from where the last step's body got to
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


class Linearization:
    """The step's system at (or next to) its solution, for adjoint/forward sensitivities.

    dof_map: [3(N+Nb)] reduced row of each DOF (-1 = prescribed). matrix: the last projected
    Newton matrix (CSR over the reduced DOFs). factorization: its Cholesky factor, computed on
    first access (the Newton solve itself may have used an older factor as a CG
    preconditioner, solver.NewtonLinearSolver). hessian: exact unprojected ∇²E at the solution
    (CSR over the free DOFs), or None unless SimSettings.keep_linearization.
    """

    def __init__(self, dof_map: np.ndarray, matrix, hessian=None, factorization=None):
        self.dof_map = dof_map
        self.matrix = matrix
        self.hessian = hessian
        self._factorization = factorization

    @property
    def factorization(self) -> Factorization | None:
        if self._factorization is None and self.matrix is not None:
            self._factorization = Factorization(self.matrix)
        return self._factorization


class SurfaceCarry:
    """Points carried rigidly by their closest triangles of a deforming surface.

    Each point p is written as q + δ, q = Σ w_k v_k the closest point on a triangle (barycentric
    w) and δ in that triangle's orthonormal frame (first edge, in-plane normal, face normal);
    ``at(V)`` rebuilds the points on the surface posed as V. Exact for a rigid motion of each
    triangle. The closest triangle is searched among the k with the nearest centroids: not
    always the global one (a long triangle's centroid can be far), which only matters where
    the carry is a heuristic (the solver's start, checked by CCD).

    Attributes: distance [m] (|δ|), face, bary, side (+1 where p lies on the normal's side).
    """

    def __init__(self, V, F, P, k=8):
        from scipy.spatial import cKDTree

        from ..geometry import closest_point_triangle

        V, P = np.asarray(V, dtype=np.float64), np.asarray(P, dtype=np.float64)
        self.F = np.asarray(F, dtype=np.int64)
        k = min(k, len(self.F))
        _, cand = cKDTree(V[self.F].mean(1)).query(P, k=k)
        cand = cand.reshape(len(P), k)
        t = self.F[cand.ravel()]
        Pr = np.repeat(P, k, axis=0)
        w = closest_point_triangle(Pr, V[t[:, 0]], V[t[:, 1]], V[t[:, 2]])
        q = np.einsum("nk,nkd->nd", w, V[t])
        dist = np.linalg.norm(Pr - q, axis=1).reshape(len(P), k)
        j = np.argmin(dist, axis=1)
        r = np.arange(len(P))
        self.distance = dist[r, j]
        self.face = cand[r, j]
        self.bary = w.reshape(len(P), k, 3)[r, j]
        q = q.reshape(len(P), k, 3)[r, j]
        R, _ = self._frames(V)
        self.local = np.einsum("mij,mj->mi", R, P - q)
        self.side = np.where(self.local[:, 2] < 0, -1.0, 1.0)

    def _frames(self, V):
        tri = V[self.F[self.face]]  # [m, 3 (vertex), 3]
        e1 = tri[:, 1] - tri[:, 0]
        nrm = np.cross(e1, tri[:, 2] - tri[:, 0])
        e1 = e1 / np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-300)
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        return np.stack([e1, np.cross(nrm, e1), nrm], axis=1), tri  # rows: the frame's axes

    def at(self, V, lift=None):
        """The carried points on the surface posed as V [Nv, 3]; ``lift`` [m] (per point) is
        added along the face normal."""
        R, tri = self._frames(np.asarray(V, dtype=np.float64))
        P = np.einsum("mk,mkd->md", self.bary, tri) + np.einsum("mij,mi->mj", R, self.local)
        if lift is not None:
            P = P + np.asarray(lift)[:, None] * R[:, 2]
        return P


class ClothSim:
    """Implicit-Euler C-IPC cloth simulator for one garment against one moving body.

    Args:
        rest_vertices: [N, 3] garment rest positions (its stress-free shape).
        faces: [F, 3] consistently oriented triangles.
        material: :class:`Material`.
        settings: :class:`SimSettings`.
        boundary_indices: [K] Dirichlet vertices (follow prescribed targets every step).
    """

    def __init__(self, rest_vertices, faces, material: Material, settings: SimSettings = SimSettings(),
                 boundary_indices=()):
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
        self.scene = None
        self.barrier_stiffness = 0.0
        self.max_barrier_stiffness = 0.0
        self._kappa_balanced = False
        self.linearization = None
        self._body_faces = None
        self.linear_solver = NewtonLinearSolver(settings.linear_rtol, settings.max_cg_iterations)
        # The penalty-mode system (body DOFs unknown too) keeps its own preconditioner, so
        # switching between the two systems within a step costs no refactorisation. Its path
        # decides where the body is snapped and friction re-lagged, so it is solved to 1e-10
        # (as exact as a direct solve: the ρ-scaling invariance test holds to 1e-5 only then).
        self.linear_solver_all = NewtonLinearSolver(1e-10, settings.max_cg_iterations)

    # -- setup ---------------------------------------------------------------------------------

    def _setup(self, body_vertices, body_faces):
        s, m = self.settings, self.material
        body_faces = np.asarray(body_faces, dtype=np.int64).reshape(-1, 3)
        self._body_faces = body_faces
        self.nb = len(body_vertices)
        self.linear_solver.reset()  # a different system: its factor is no preconditioner
        self.linear_solver_all.reset()
        n_total = self.n + self.nb
        self.scene = ContactScene(self.topo.rest, self.topo.faces, body_vertices, body_faces,
                                  s.dhat, s.dmin, s.self_contact)
        self.scene.ccd_threads = s.ccd_threads if s.deterministic else 0
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
            self.mass_damping = MassDamping(self.inertia, s.damping_mass)
            self.terms.append(self.mass_damping)
        if s.damping_stiffness > 0:
            self.stiffness_damping = StiffnessDamping(s.damping_stiffness, self.h_implicit, [self.membrane, self.bending])
            self.terms.append(self.stiffness_damping)
        mean_mass = m.density * float(np.mean(self.topo.vertex_area))
        kinematic = np.r_[self.boundary, np.arange(self.n, n_total)]
        self.penalty = KinematicPenalty(kinematic, s.kinematic_penalty * mean_mass / self.h_implicit**2, n_total)
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
        self._average_mass = mean_mass / self.h_implicit**2
        self._n_free = max(1, self.n - len(self.boundary))

    def reset(self):
        """Forget the adaptive barrier stiffness (it persists across steps, as in IPC)."""
        self.barrier_stiffness = 0.0
        self.max_barrier_stiffness = 0.0
        self._kappa_balanced = False

    # -- energy --------------------------------------------------------------------------------

    def _energy(self, X, penalty):
        total = 0.0
        for t in self._active_terms(penalty):
            total += t.energy(X)
            if not np.isfinite(total):
                return np.inf
        return total

    def _active_terms(self, penalty):
        terms = self.terms + [self.barrier, self.friction]
        return terms + [self.penalty] if penalty else terms

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
        s = self.settings
        h = s.dt
        t_start = time.perf_counter()
        # ipctk's threaded reductions sum in a scheduling-dependent order; one thread makes a
        # step bit-reproducible (DESIGN.md: same inputs, same outputs).
        if s.deterministic:
            ipctk.set_num_threads(1)
        stats = StepStats()
        x = np.asarray(x, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        if collider_vertices_t is None:  # no body: an empty collider
            collider_vertices_t = collider_vertices_t1 = np.zeros((0, 3))
            collider_faces = np.zeros((0, 3), dtype=np.int64)
        bt = np.asarray(collider_vertices_t, dtype=np.float64).reshape(-1, 3)
        bt1 = np.asarray(collider_vertices_t1, dtype=np.float64).reshape(-1, 3)
        if (self.scene is None or len(bt) != self.nb
                or not np.array_equal(np.asarray(collider_faces).reshape(-1, 3), self._body_faces)):
            self._setup(bt, collider_faces)
        lag, self._body_lag = self._body_lag, None
        if lag is not None and np.array_equal(lag[0], bt):
            bt = lag[1]  # the last step's body stopped short of this pose: go on from where it is
            stats.body_lagged = True
        X_prev = np.vstack([x, bt])
        # x̃ = x̂ + ĥ v̂: implicit Euler (x̂, v̂ = xₜ, vₜ; ĥ = h) or BDF2 (ĥ = 2h/3); friction and
        # damping measure velocities as (x − x̂) / ĥ, the body's from the matching constant-
        # velocity base (exact for a body moving at constant velocity)
        base, vbase, hh = self.step_base(x, v, history)
        self._set_implicit_step(hh)
        X_base = np.vstack([base, bt + (1.0 - hh / h) * (bt1 - bt)])
        x_pred = base + hh * vbase
        X_goal = X_prev.copy()
        X_goal[self.n:] = bt1
        if len(self.boundary) and boundary_targets is not None:
            X_goal[self.boundary] = np.asarray(boundary_targets, dtype=np.float64)
        self.inertia.target = np.vstack([x_pred, bt1])
        if s.damping_mass > 0:
            self.mass_damping.previous = X_base
        if s.damping_stiffness > 0:
            self.stiffness_damping.begin_step(X_prev)
        self.penalty.target = X_goal[self.penalty.kinematic]

        tc = time.perf_counter()
        alpha = self.scene.collision_free_stepsize(X_prev, X_goal)
        stats.time["ccd"] += time.perf_counter() - tc
        penalty = alpha < 1.0
        X = X_prev.copy() if penalty else X_goal.copy()
        if penalty and s.follow_body > 0 and self.nb:
            X, reached = self._follow_body(X_prev, X_goal, x_pred, stats)
            penalty = not reached
            stats.body_follows += int(reached)
        elif not penalty and s.warm_start and np.any(x_pred != x):
            X = self._warm_start(X, x_pred, stats)

        diag = self.scene.bbox_diagonal(X_goal)
        self.scene.prepare_static(X)
        self._update_stiffness_init(X)
        lag_left = max(1, s.friction_iterations)
        self.friction.lag(X, self.barrier, X_base)
        lag_left -= 1
        prev_min_dist = self.scene.min_distance(X)
        prev_residual = np.inf
        below_count = 0  # consecutive directions below newton_tol ("rms")
        factor = None
        penalty_iters = 0
        solvers = (self.linear_solver, self.linear_solver_all)
        for ls in solvers:  # the last step's factors no longer fit (body, x̃, contacts moved)
            ls.mark_stale()
        linear_solver = self.linear_solver
        n_fact0 = sum(ls.factorizations for ls in solvers)
        n_cg0 = sum(ls.cg_iterations for ls in solvers)
        for it in range(s.max_newton_iterations):
            stats.newton_iterations = it + 1
            assembler = self.assembler_all if penalty else self.assembler_free
            self._update_stiffness_init(X)
            active = self._active_terms(penalty)
            # gradient and Hessian
            ta = time.perf_counter()
            grads_el, hess_el, grads_c, hess_c = [], [], [], []
            for t in active:
                contact = t is self.barrier or t is self.friction
                tt = time.perf_counter()
                g = t.gradient(X)
                H = t.hessian(X, project=True)
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
            # Newton direction
            tl = time.perf_counter()
            # Penalty iterations solve their (larger) system by CG too (to 1e-10, see
            # linear_solver_all): a direct solve of it (full hinge pattern) cost ~4 sparsified
            # factorisations per iteration on the demo dress.
            linear_solver = self.linear_solver_all if penalty else self.linear_solver
            # inexact Newton: a loose direction while far from the solution (the stopping
            # step is refined to 1e-10 below, so the solution is unchanged)
            forcing = None if penalty else s.newton_forcing
            dx = -linear_solver.solve(Hm, grad, assembler, forcing)
            factor = Hm
            stats.time["linear_solve"] += time.perf_counter() - tl
            step = assembler.expand(dx).reshape(-1, 3)
            residual, res_stop = self._residuals(step, h)
            if not penalty and res_stop < s.newton_tol:  # about to stop: make dx exact first
                tl = time.perf_counter()
                dx = -self.linear_solver.refine(Hm, grad, -dx, assembler)
                stats.time["linear_solve"] += time.perf_counter() - tl
                step = assembler.expand(dx).reshape(-1, 3)
                residual, res_stop = self._residuals(step, h)
            stats.residual = res_stop
            below = not penalty and res_stop < s.newton_tol
            if s.newton_norm == "max" and below:  # the step is not taken: it is below tolerance
                if lag_left > 0:
                    self.friction.lag(X, self.barrier, X_base)
                    lag_left -= 1
                    continue
                stats.converged = True
                break
            # "rms" (Codim-IPC): the step is taken, and the solve ends once the last
            # newton_window directions were all below the tolerance
            below_count = below_count + 1 if below else 0
            stop_after_step = s.newton_norm == "rms" and below_count >= s.newton_window
            # line search from the collision-free step size
            tcd = time.perf_counter()
            X_try = X + step
            alpha = self.scene.collision_free_stepsize(X, X_try)
            self.scene.covers_last_point = True  # X + α step, α ≤ 1, lies on this segment
            stats.time["ccd"] += time.perf_counter() - tcd
            tls = time.perf_counter()
            E0 = self._energy(X, penalty)
            while True:
                X_new = X + alpha * step
                E1 = self._energy(X_new, penalty)
                if E1 <= E0 or alpha < 1e-12:
                    break
                alpha *= 0.5
                stats.line_search_iterations += 1
            if (s.step_expansion and not penalty and alpha == 1.0
                    and residual > 0.7 * prev_residual):
                X_new = self._expand_step(X, step, X_new, E1, stats)
            prev_residual = residual
            X = X_new
            stats.time["line_search"] += time.perf_counter() - tls
            # adaptive barrier stiffness (ipctk): grow κ when contacts keep closing in
            tc = time.perf_counter()
            min_dist = self.scene.min_distance(X)
            if self.max_barrier_stiffness > 0 and np.isfinite(min_dist) and np.isfinite(prev_min_dist):
                k = ipctk.update_barrier_stiffness(prev_min_dist, min_dist, self.max_barrier_stiffness,
                                                   self.barrier_stiffness, diag, dmin=s.dmin)
                if k != self.barrier_stiffness:
                    self.barrier_stiffness = k
                    self.barrier.set_stiffness(k)
            prev_min_dist = min_dist
            stats.time["contact"] += time.perf_counter() - tc
            if penalty:
                penalty_iters += 1
                gap = np.max(np.abs(X[self.penalty.kinematic] - self.penalty.target))
                if gap < 1e-2 * s.dhat:
                    X_snap = X.copy()
                    X_snap[self.penalty.kinematic] = self.penalty.target
                    tcd = time.perf_counter()
                    ok = self.scene.collision_free_stepsize(X, X_snap) >= 1.0
                    stats.time["ccd"] += time.perf_counter() - tcd
                    if ok:
                        X = X_snap
                        penalty = False
                        self.scene.prepare_static(X)
                        self.friction.lag(X, self.barrier, X_base)
                    else:
                        # The cloth sits closer to the body than the body's remaining gap:
                        # the barrier holds the body short of its target at this penalty
                        # weight, and more iterations at the same weight do not move it (a
                        # pinched coarse proxy looped here to the iteration limit, thousands
                        # of line-search halvings). A stiffer penalty pushes the cloth on.
                        self.penalty.weight *= 10.0
                        if penalty_iters >= s.max_penalty_iterations:
                            break
                        continue
                elif s.follow_body > 0 and s.follow_retry > 0 and penalty_iters % s.follow_retry == 0:
                    # try again to carry the cloth the rest of the way (the pairs that cut the
                    # first try may have separated)
                    X_f, reached = self._follow_body(X, X_goal, None, stats)
                    self.scene.prepare_static(X_f if reached else X)
                    if reached:
                        X = X_f
                        penalty = False
                        stats.body_follows += 1
                        self.friction.lag(X, self.barrier, X_base)
                if penalty and penalty_iters >= s.max_penalty_iterations:
                    break  # no room for the cloth at the body's pose: keep what was reached
                if penalty and penalty_iters % 10 == 0:
                    self.penalty.weight *= 10.0  # AL-style escalation when targets stall
                    continue
            # The candidates of the last CCD segment (X → X + t·step, inflated by d̂) hold every
            # pair within d̂ of any point on it, X_new included: no rebuild needed for the next
            # iteration's barrier set (one LBVH build per iteration instead of two).
            if not self.scene.covers_last_point:
                self.scene.prepare_static(X)
            if stop_after_step:
                if lag_left > 0:
                    self.friction.lag(X, self.barrier, X_base)
                    lag_left -= 1
                    below_count = 0
                    continue
                stats.converged = True
                break
        stats.penalty_iterations = penalty_iters
        stats.factorizations = sum(ls.factorizations for ls in solvers) - n_fact0
        stats.cg_iterations = sum(ls.cg_iterations for ls in solvers) - n_cg0
        if penalty:  # never reached the targets: report, keep the best state, let the body lag
            stats.converged = False
            stats.body_gap = float(np.max(np.linalg.norm(X[self.penalty.kinematic] - self.penalty.target, axis=1)))
            self._body_lag = (bt1.copy(), X[self.n:].copy())
        X_final = X
        stats.barrier_stiffness = self.barrier_stiffness
        self.scene.prepare_static(X_final)
        c = self.scene.collisions_at(X_final)
        stats.n_contacts = len(c)
        stats.min_distance = float(np.sqrt(self.scene.min_distance(X_final)))  # ipctk: squared
        self.linearization = Linearization(
            (self.assembler_all if penalty else self.assembler_free).dof_map, factor,
            factorization=(linear_solver.factor if linear_solver.factor_matrix is factor else None),
        )
        if s.keep_linearization and not penalty:
            hess = [t.hessian(X_final, project=False) for t in self._active_terms(False)]
            self.linearization.hessian = self.assembler_free.assemble(hess)
        x_new = X_final[: self.n].copy()
        v_new = (x_new - base) / hh
        self._last_step = (x_new, v_new, x.copy(), v.copy())
        stats.time["total"] = time.perf_counter() - t_start
        return x_new, v_new, stats

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

    def _set_implicit_step(self, hh):
        """Make every h-dependent term use the implicit step ĥ (h, or BDF2's 2h/3)."""
        self.h_implicit = hh  # also resets the penalty weight the last step may have stiffened
        self.inertia.dt = hh  # mass damping reads it from here
        self.friction.dt = hh
        if self.settings.damping_stiffness > 0:
            self.stiffness_damping.dt = hh
        mean_mass = self.material.density * float(np.mean(self.topo.vertex_area))
        self.penalty.weight = self.settings.kinematic_penalty * mean_mass / hh**2
        self._average_mass = mean_mass / hh**2

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

    def _warm_start(self, X, x_pred, stats):
        """Start Newton from the inertial prediction x̃ = xₜ + h vₜ (free vertices), clipped by
        CCD so it stays intersection-free, when its energy is below that of xₜ (IPC's
        initial guess; the minimiser is the same, only the path to it changes)."""
        X_pred = X.copy()
        free = self.inertia.unit_mass[: self.n] > 0
        X_pred[: self.n][free] = x_pred[free]
        tc = time.perf_counter()
        alpha = self.scene.collision_free_stepsize(X, X_pred)
        stats.time["ccd"] += time.perf_counter() - tc
        if alpha <= 0.0:
            return X
        X_pred = X + alpha * (X_pred - X)
        terms = self.terms + [self.barrier]  # friction is not lagged yet at this point
        self.scene.prepare_static(X)
        e0 = sum(t.energy(X) for t in terms)
        self.scene.prepare_static(X_pred)
        e1 = sum(t.energy(X_pred) for t in terms)
        return X_pred if e1 < e0 else X

    def _follow_body(self, X_from, X_goal, x_pred, stats):
        """Carry the cloth along with the body from X_from to the body pose of X_goal
        (SimSettings.follow_body). Returns (X, reached): X_goal's body with the carried cloth
        when every leg of the move is collision-free (reached = True), else X_from moved by
        the collision-free part of the move (reached = False).

        Free cloth vertices within ``follow_body`` of the body move rigidly with their closest
        body triangle (SurfaceCarry), fading to x_pred (the inertial prediction; None = stay)
        at twice that distance. The body's vertices move on straight lines, a carried point on
        a rotating triangle does not, and a straight cloth path dips towards the triangle by
        ~θ²L/8 (tens of µm, more than the µm gaps of resting contacts): the cloth follows its
        triangles through ``follow_segments`` intermediate body poses, each leg CCD-checked.
        Cloth in an active contact (within d̂, from the barrier's collision set) is also lifted
        off along the triangle normal, up to ``follow_lift`` × d̂ by the end: those gaps would
        not survive the small non-rigid distortions of the carry; the free phase settles it
        back in a few iterations.
        """
        s = self.settings
        n = self.n
        free = np.flatnonzero(self.inertia.unit_mass[:n] > 0)
        b0, b1 = X_from[n:], X_goal[n:]
        x = X_from[:n][free]
        x_end = x if x_pred is None else x_pred[free]
        tq = time.perf_counter()
        carry = SurfaceCarry(b0, self._body_faces, x)
        weight = np.clip(2.0 - carry.distance / s.follow_body, 0.0, 1.0)[:, None]
        gap = np.full(n, np.inf)  # per cloth vertex: the closest active contact it is part of
        self.scene.prepare_static(X_from)
        coll = self.scene.collisions_at(X_from)
        E, Fa = self.scene.mesh.edges, self.scene.mesh.faces
        for group in (coll.vv_collisions, coll.ev_collisions, coll.ee_collisions, coll.fv_collisions):
            for c in group:
                ids = [i for i in c.vertex_ids(E, Fa) if i >= 0]
                cloth = [i for i in ids if i < n]
                gap[cloth] = np.minimum(gap[cloth], np.sqrt(max(c.compute_distance(X_from[ids].ravel()), 0.0)))
        gap = np.minimum(gap[free], carry.distance)
        lift = np.clip(s.follow_lift * s.dhat - gap, 0.0, None) * carry.side
        stats.time["contact"] += time.perf_counter() - tq
        X_seg = X_from
        K = max(1, int(s.follow_segments))
        for k in range(1, K + 1):
            t = k / K
            X_next = X_goal.copy() if k == K else X_from + t * (X_goal - X_from)
            carried = carry.at(X_next[n:], lift=t * lift)
            X_next[:n][free] = weight * carried + (1.0 - weight) * (x + t * (x_end - x))
            tc = time.perf_counter()
            alpha = self.scene.collision_free_stepsize(X_seg, X_next)
            stats.time["ccd"] += time.perf_counter() - tc
            if alpha < 1.0:
                return X_seg + alpha * (X_next - X_seg), False
            X_seg = X_next
        return X_seg, True

    def _expand_step(self, X, step, X_new, E_new, stats, max_scale=64.0):
        """Try X + 2·step, 4·step, ... while the energy keeps decreasing; a move that CCD cuts is
        tried at its collision-free fraction and ends the search. Returns the best point.

        Projected Newton converges only linearly along a mode whose curvature the PSD
        projection overstates: e.g. a vertex sliding over a body vertex, where the barrier's
        negative tangential curvature is clamped away. The full step is then accepted every
        iteration while the residual shrinks by a constant ratio (0.96 measured on the demo
        dress: 30 iterations for one vertex). Doubling the step along that direction reaches the
        same minimiser in a few energy evaluations; the stopping rule is unchanged.
        """
        scale = 1.0
        while scale < max_scale:
            X_try = X + (2.0 * scale) * step
            tc = time.perf_counter()
            a = self.scene.collision_free_stepsize(X, X_try)
            stats.time["ccd"] += time.perf_counter() - tc
            last = a < 1.0  # the doubled step is cut by CCD: take its collision-free part, stop
            if last:
                if 2.0 * scale * a <= scale * 1.05:
                    # that segment (ending at 2·scale·a·step) may stop short of X_new
                    self.scene.covers_last_point = 2.0 * scale * a >= scale
                    break
                X_try = X + (2.0 * scale * a) * step
            E_try = self._energy(X_try, False)
            if not E_try < E_new:
                break
            scale = 2.0 * scale * a if last else 2.0 * scale
            X_new, E_new = X_try, E_try
            stats.step_expansions += 1
            if last:
                break
        return X_new

    def _update_stiffness_init(self, X):
        """ipctk's initial κ from the balance of elastic and barrier gradients (IPC Sec. 4.3).

        Before any contact κ is ipctk's minimum (scaled by mass); the first time contacts
        exist it is set from the gradient balance; afterwards it only grows through
        update_barrier_stiffness and persists across steps, as in IPC.
        """
        if self._kappa_balanced:
            return
        c = self.scene.collisions_at(X)
        if self.barrier_stiffness > 0 and not len(c):
            return
        grad_e = np.sum([t.gradient(X) for t in self.terms], axis=0)
        unit = ipctk.BarrierPotential(self.settings.dhat, 1.0)
        grad_b = unit.gradient(c, self.scene.mesh, X) if len(c) else np.zeros_like(grad_e)
        k, kmax = ipctk.initial_barrier_stiffness(
            self.scene.bbox_diagonal(X), unit.barrier, self.settings.dhat, self._average_mass,
            grad_e, grad_b, self.settings.barrier_stiffness_scale, self.settings.dmin,
        )
        self._kappa_balanced = bool(len(c))
        self.barrier_stiffness = max(k, self.barrier_stiffness)
        self.max_barrier_stiffness = max(kmax, self.max_barrier_stiffness)
        self.barrier.set_stiffness(self.barrier_stiffness)


def simulate(garment_rest, faces, material: Material, collider_sequence, collider_faces,
             boundary_indices=(), boundary_targets=None, fps: float = 25.0, substeps: int = 1,
             settings: SimSettings | None = None, x0=None, v0=None, callback=None,
             progress: bool = False):
    """Simulate a garment on a moving body for a whole sequence.

    Args:
        garment_rest: [N, 3] rest shape (also the initial state unless ``x0`` is given).
        faces: [F, 3] garment triangles.
        material: :class:`Material`.
        collider_sequence: [T, Nb, 3] body vertices per frame (frame 0 = initial pose).
        collider_faces: [Fb, 3] body triangles.
        boundary_indices: [K] Dirichlet vertices.
        boundary_targets: [T, K, 3] their positions per frame, or a callable
            ``rule(frame, body_vertices [Nb, 3]) -> [K, 3]`` (an attachment rule), or None
            (they stay at their initial positions).
        fps: frames per second of the sequence; substeps: implicit steps per frame
            (dt = 1 / (fps · substeps); body and targets are interpolated linearly in between).
        settings: :class:`SimSettings` (its dt is replaced by the one above); default: the
            defaults with the material's integrator (the one it was fitted with).
        x0, v0: [N, 3] initial positions / velocities (default rest, zero).
        callback: called as ``callback(frame, x [N, 3], stats list)`` after each frame.
        progress: show a rich progress bar.

    Returns:
        [T, N, 3] garment positions per frame (frame 0 = initial state).
    """
    settings = settings or SimSettings(integrator=material.integrator)  # the model it was fitted in
    dt = 1.0 / (fps * substeps)
    settings = dataclasses.replace(settings, dt=dt)
    bodies = np.asarray(collider_sequence, dtype=np.float64)
    T = len(bodies)
    sim = ClothSim(garment_rest, faces, material, settings, boundary_indices)
    order = np.argsort(np.asarray(boundary_indices, dtype=np.int64), kind="stable")
    x = np.array(garment_rest if x0 is None else x0, dtype=np.float64)
    v = np.zeros_like(x) if v0 is None else np.array(v0, dtype=np.float64)

    def targets(frame):
        if len(sim.boundary) == 0:
            return None
        if boundary_targets is None:
            return x0_boundary
        if callable(boundary_targets):
            return np.asarray(boundary_targets(frame, bodies[frame]))[order]
        return np.asarray(boundary_targets[frame])[order]

    x0_boundary = x[sim.boundary].copy()
    out = np.empty((T,) + x.shape)
    out[0] = x
    bar = None
    if progress:
        from rich.progress import Progress

        bar = Progress()
        bar.start()
        task = bar.add_task("simulating", total=T - 1)
    try:
        for f in range(1, T):
            stats_frame = []
            tb0, tb1 = targets(f - 1), targets(f)
            for k in range(substeps):
                w0, w1 = k / substeps, (k + 1) / substeps
                b0 = (1 - w0) * bodies[f - 1] + w0 * bodies[f]
                b1 = (1 - w1) * bodies[f - 1] + w1 * bodies[f]
                tgt = None if tb1 is None else (1 - w1) * tb0 + w1 * tb1
                x, v, st = sim.step(x, v, b0, b1, collider_faces, tgt)
                stats_frame.append(st)
            out[f] = x
            if callback is not None:
                callback(f, x, stats_frame)
            if bar is not None:
                bar.update(task, advance=1)
    finally:
        if bar is not None:
            bar.stop()
    return out
