"""Contact terms from the IPC Toolkit: barrier potential, lagged friction, CCD.

Cloth and body share one ipctk CollisionMesh: vertices [cloth (N); body (Nb)]. Body vertices
are prescribed; a collision filter rejects body–body pairs and, unless garment self-contact is
on, cloth–cloth pairs. Nothing of the contact model is written here: distances, barrier,
friction, CCD and the adaptive stiffness are ipctk's; this module only keeps their state and
exposes the term protocol (terms.py) on the stacked positions X [N + Nb, 3].
"""

from __future__ import annotations

from operator import attrgetter

import ipctk
import numpy as np

from .terms import Diagonal, HessianSum, SparseHessian, StepState, StepTangent, Term


class ContactScene:
    """The shared collision mesh plus the collision state reused by the contact terms.

    ``candidate_filter``: None, or a callable given the scene after every candidate build, which
    may drop primitive pairs from ``scene.candidates`` (ipctk's ``can_collide`` works on vertex
    pairs only; a crease step's contact with the visible part of a body triangle, sim.crease).

    Args:
        cloth_rest: [N, 3]; cloth_faces: [F, 3]; body_rest: [Nb, 3]; body_faces: [Fb, 3].
        dhat: barrier activation distance [m]; dmin: minimum separation (thickness) [m].
        self_contact: also resolve cloth–cloth contact.
        exclude: [P, 2] cloth vertex pairs never in contact with each other, nor the edges and
            faces holding them (ipctk's filter: a pair of primitives is skipped when every pair
            of their vertices is excluded); e.g. a sewn seam's neighbourhood (sim.simulate.seam_exclusions).
        prescribed: [K] cloth vertices whose motion is prescribed (the solver's Dirichlet
            vertices). Like body–body pairs, primitive pairs made only of prescribed vertices
            (these and the body's) are left out: no unknown can move them apart, so their
            barrier only holds the prescribed motion back (the kinematic-penalty phase stalls
            and the body lags) and their closing distance drives κ up (docs/simulation.md
            "Prescribed pairs").
    """

    candidate_filter = None  # see above; set per scene

    def __init__(self, cloth_rest, cloth_faces, body_rest, body_faces, dhat, dmin=0.0,
                 self_contact=False, ccd_rescaling=0.9, exclude=None, prescribed=None):
        self.n_cloth = len(cloth_rest)
        self.n_body = len(body_rest)
        faces = np.vstack([cloth_faces, np.asarray(body_faces) + self.n_cloth]).astype(np.int32)
        rest = np.vstack([cloth_rest, body_rest]).astype(np.float64)
        self.faces = faces
        self.mesh = ipctk.CollisionMesh(rest, ipctk.edges(faces), faces)
        if self_contact:
            # Only body–body pairs are rejected (both vertices ≥ n_cloth).
            self.mesh.can_collide = cloth_filter(self.n_cloth, exclude)
        else:
            patch = np.r_[np.zeros(self.n_cloth), np.ones(self.n_body)].astype(np.int32)
            self.mesh.can_collide = ipctk.make_vertex_patches_filter(patch)
        if prescribed is not None and len(prescribed):
            self.mesh.can_collide = self.mesh.can_collide & prescribed_filter(self.n_cloth, self.n_body, prescribed)
        self.dhat = float(dhat)
        self.dmin = float(dmin)
        # ipctk inflates every primitive's box by this radius, so a build holds every pair
        # within twice it (ipctk's own NormalCollisions.build inflates by (d̂ + dmin) / 2)
        self.inflation = self.dhat + self.dmin
        self._preview = (None, None)  # (X, NormalCollisions within the preview distance) of the last call
        # AdditiveCCD (C-IPC's CCD; far faster than Tight Inclusion on cloth sliding along the
        # body, docs/simulation.md "The step"), with a conservative 10% margin of the initial
        # separation.
        self.ccd = ipctk.AdditiveCCD(conservative_rescaling=ccd_rescaling)
        self.broad_phase = ipctk.LBVH()
        self.candidates = ipctk.Candidates()
        self.collisions = ipctk.NormalCollisions()
        self._collisions_at = None
        self.covers_last_point = False  # solver bookkeeping: candidates valid at its iterate
        self.ccd_threads = 1  # narrow-phase CCD threads (order-independent; ClothSim sets it)
        # candidate-build threads (ClothSim sets it; ≤ 1: ipctk's setting, one thread in the
        # deterministic solver); with more the candidates come in a schedule-dependent order, so
        # ``canonical`` must be on: barrier sets in a canonical order (canonical_order)
        self.build_threads = 1
        self.canonical = False

    # -- collision sets ------------------------------------------------------------------------

    def prepare_static(self, X):
        """Candidates around one configuration (inflated by d̂): valid for X only."""
        with ipctk_threads(self.build_threads):
            self.candidates.build(self.mesh, X, self.inflation, self.broad_phase)
        if self.candidate_filter is not None:
            self.candidate_filter(self)
        self._collisions_at = None
        self._preview = (None, None)

    def prepare_segment(self, X0, X1):
        """Candidates for the whole segment X0 → X1: valid for every point on it."""
        with ipctk_threads(self.build_threads):
            self.candidates.build(self.mesh, X0, X1, self.inflation, self.broad_phase)
        if self.candidate_filter is not None:
            self.candidate_filter(self)
        self._collisions_at = None
        self._preview = (None, None)

    def collisions_at(self, X):
        """The active barrier set at X (from the current candidates; cached for repeated X)."""
        if self._collisions_at is None or not np.array_equal(self._collisions_at, X):
            self.collisions.build(self.candidates, self.mesh, X, self.dhat, self.dmin)
            if self.canonical:
                canonical_order(self.collisions)
            self._collisions_at = X.copy()
        return self.collisions

    def preview_collisions(self, X, distance):
        """The pairs within ``distance`` (≤ 2 :attr:`inflation` − dmin) of each other at X, from the
        current candidates (a build that covers X), as an ipctk NormalCollisions with d̂ =
        ``distance`` (cached for X): the solver's contact preview (ClothSim._newton_direction)."""
        X0, c = self._preview
        if c is None or not np.array_equal(X0, X):
            c = ipctk.NormalCollisions()
            c.build(self.candidates, self.mesh, X, distance, self.dmin)
            if self.canonical:
                canonical_order(c)
            self._preview = (X.copy(), c)
        return c

    def collision_free_stepsize(self, X0, X1):
        """Largest α ∈ [0, 1] such that X0 + α (X1 − X0) stays intersection-free (ipctk CCD).

        The narrow phase runs on ``ccd_threads`` threads: it is a min-reduction over the
        candidates (each candidate's time of impact does not depend on the others), so the
        result is the same bits on any number of threads and in any candidate order. The
        candidate build runs on ``build_threads``: with more than one its candidates come in a
        schedule-dependent order, which the barrier sets built from them do not keep when
        ``canonical`` is on (:func:`canonical_order`).
        """
        self.prepare_segment(X0, X1)
        with ipctk_threads(self.ccd_threads):
            return self.candidates.compute_collision_free_stepsize(
                self.mesh, X0, X1, self.dmin, self.ccd
            )

    def min_distance(self, X):
        c = self.collisions_at(X)
        return c.compute_minimum_distance(self.mesh, X) if len(c) else np.inf

    def has_intersections(self, X):
        return ipctk.has_intersections(self.mesh, X)

    def bbox_diagonal(self, X):
        return ipctk.world_bbox_diagonal_length(X)


class ipctk_threads:
    """``with ipctk_threads(k)``: ipctk (TBB) on k threads inside, its setting before after (one
    in the deterministic solver, ClothSim.step); k ≤ 1 leaves ipctk's setting alone."""

    def __init__(self, k: int):
        self.k = int(k)
        self.before = None

    def __enter__(self):
        if self.k > 1:
            self.before = ipctk.get_num_threads()
            ipctk.set_num_threads(self.k)

    def __exit__(self, *exc):
        if self.k > 1:
            ipctk.set_num_threads(self.before)


_ORDER_KEYS = (("vv_collisions", ("vertex0_id", "vertex1_id")), ("ev_collisions", ("edge_id", "vertex_id")),
               ("ee_collisions", ("edge0_id", "edge1_id")), ("fv_collisions", ("face_id", "vertex_id")))


def canonical_order(collisions):
    """Put an ipctk NormalCollisions in a canonical order, in place: each kind (vertex–vertex,
    edge–vertex, edge–edge, face–vertex) sorted by its primitive ids, and each vertex–vertex pair
    as (smaller id, larger id). ipctk builds a barrier set in the order of the candidates it is
    given, and every sum over it (energy, gradient, Hessian, friction) in that order; a candidate
    build on several threads lists the same candidates in a schedule-dependent order, and a
    vertex pair that several candidates reduce to (IPC's set merges them, with integer weights)
    keeps the orientation of the first. Canonical, the set and its sums are the same bits for
    any candidate order, hence any number of build threads (docs/simulation.md "Session 32").
    A pair of primitives is one collision, so the ids are a total order. A few hundred
    collisions a set on the demo dress: 1.1–1.3 ms, mostly pybind11 attribute access."""
    for kind, (a, b) in _ORDER_KEYS:
        items = getattr(collisions, kind)
        if not items:
            continue
        changed = False
        if kind == "vv_collisions":
            for c in items:
                if c.vertex0_id > c.vertex1_id:
                    c.vertex0_id, c.vertex1_id = c.vertex1_id, c.vertex0_id
                    changed = True
        keys = list(map(attrgetter(a, b), items))
        order = sorted(range(len(keys)), key=keys.__getitem__)
        if changed or any(i != j for i, j in enumerate(order)):
            setattr(collisions, kind, [items[i] for i in order])


def cloth_filter(n_cloth: int, exclude=None):
    """ipctk filter: no body–body pairs (vertices ≥ n_cloth) and none of the ``exclude`` pairs [P, 2]."""
    static = ipctk.make_static_obstacle_filter(n_cloth)
    if exclude is None or not len(exclude):
        return static
    pairs = np.sort(np.asarray(exclude, dtype=np.int64).reshape(-1, 2), axis=1)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    return static & ipctk.make_sparse_filter(dict.fromkeys(map(tuple, pairs.tolist()), False), True)


def prescribed_filter(n_cloth: int, n_body: int, prescribed):
    """ipctk filter: no pair of two prescribed vertices (the cloth vertices ``prescribed`` [K]
    and every body vertex): each free cloth vertex is its own patch, the prescribed ones one
    patch together (ipctk then skips a primitive pair only when all its vertex pairs are)."""
    patch = np.r_[np.arange(1, n_cloth + 1), np.zeros(n_body)].astype(np.int32)
    patch[np.asarray(prescribed, dtype=np.int64)] = 0
    return ipctk.make_vertex_patches_filter(patch)


class Barrier(Term):
    """κ Σ_k b(d_k(X)): ipctk's IPC log barrier over the active set (energy units, J).

    κ is adapted by ipctk's initial_barrier_stiffness / update_barrier_stiffness (solver.py);
    it scales with the average mass, so the term scales with ρ like the rest of E (its
    ``parameter``; κ's dependence on the stiffnesses through ipctk's gradient balance is not
    differentiated: docs/physics.md "Exact gradients").
    """

    parameter = "density"

    def __init__(self, scene: ContactScene, stiffness: float = 1.0):
        self.scene = scene
        self.set_stiffness(stiffness)

    def set_stiffness(self, stiffness):
        self.scale = float(stiffness)
        self.potential = ipctk.BarrierPotential(self.scene.dhat, self.scale)

    def energy(self, X):
        c = self.scene.collisions_at(X)
        return self.potential(c, self.scene.mesh, X) if len(c) else 0.0

    def gradient(self, X):
        c = self.scene.collisions_at(X)
        if not len(c):
            return np.zeros(X.size)
        return self.potential.gradient(c, self.scene.mesh, X)

    def hessian(self, X, project=True):
        c = self.scene.collisions_at(X)
        if not len(c):
            return HessianSum()
        method = ipctk.PSDProjectionMethod.CLAMP if project else ipctk.PSDProjectionMethod.NONE
        return SparseHessian(self.potential.hessian(c, self.scene.mesh, X, method))

    def preview_hessian(self, X, distance):
        """The contact preview (SimSettings.contact_preview): the PSD-projected Hessian of ipctk's
        barrier with activation distance ``distance`` (d̂₂ > d̂) and this κ, over the pairs within
        d̂₂ at X. The solver puts it in place of :meth:`hessian` in the Newton matrix of a step's
        first direction and of those after a CCD-cut step (the energy, gradient and line search keep d̂, so the step's minimiser
        is unchanged): IPC's log barrier has no curvature at d̂ and little just inside it, so a
        Newton direction carries pressed cloth through pairs that CCD then cuts the whole step at
        (docs/simulation.md "Session 20"); the d̂₂ barrier is stiffer at every gap and sees pairs
        up to d̂₂. From the current candidates (ContactScene.preview_collisions): d̂₂ ≤ 2 d̂."""
        c = self.scene.preview_collisions(X, distance)
        if not len(c):
            return HessianSum()
        potential = ipctk.BarrierPotential(distance, self.scale)
        return SparseHessian(potential.hessian(c, self.scene.mesh, X, ipctk.PSDProjectionMethod.CLAMP))


class Friction(Term):
    """Lagged IPC friction ĥ·D(v), v = (X − X̂)/ĥ, with ipctk's smoothed Coulomb potential D.

    ipctk's D is a function of velocities (eps_v in m/s). Multiplying by ĥ makes its gradient
    with respect to positions the friction force ∇_v D (the chain rule's 1/ĥ cancels, as the
    ipctk tutorial prescribes), and the Hessian (1/ĥ) ∇²_v D. X̂ (``previous``) and ĥ are the
    step's base and implicit step (:meth:`begin_step`). Normal forces λ and tangent bases are
    lagged: :meth:`lag` freezes them at one configuration (start of the step), so within the
    Newton solve the term is a smooth potential. λ = κ |b'| scales with κ, hence with mass (ρ,
    its ``parameter``).
    """

    parameter = "density"

    def __init__(self, scene: ContactScene, mu: float, eps_v: float, dt: float):
        self.scene = scene
        self.mu = float(mu)
        self.dt = float(dt)
        self.potential = ipctk.FrictionPotential(eps_v)
        self.tangential = ipctk.TangentialCollisions()
        self.previous = None

    def begin_step(self, state: StepState):
        self.dt = state.h
        self.previous = state.x_base
        self.tangential = ipctk.TangentialCollisions()

    def state_derivative(self, X, d: StepTangent):
        """∇E = ∇_v D((X − X̂)/ĥ): −H dX̂ − H (X − X̂)/ĥ dĥ, H = this term's exact Hessian
        (λ and the tangent bases held, as within the step)."""
        if not len(self.tangential):
            return None
        H = self.hessian(X, project=False).matrix
        out = -(H @ d.x_base)
        if np.any(d.h):
            out -= (H @ ((X - self.previous).ravel() / self.dt))[:, None] * d.h[None, :]
        return out

    def lag(self, X, barrier: Barrier):
        """Freeze λ and tangent bases at X (velocities are measured from the step's base)."""
        self.tangential = ipctk.TangentialCollisions()
        if self.mu > 0:
            c = self.scene.collisions_at(X)
            if len(c):
                self.tangential.build(self.scene.mesh, X, c, barrier.potential, self.mu)

    def _v(self, X):
        return (X - self.previous) / self.dt

    def energy(self, X):
        if not len(self.tangential):
            return 0.0
        return self.dt * self.potential(self.tangential, self.scene.mesh, self._v(X))

    def gradient(self, X):
        if not len(self.tangential):
            return np.zeros(X.size)
        return self.potential.gradient(self.tangential, self.scene.mesh, self._v(X))

    def hessian(self, X, project=True):
        if not len(self.tangential):
            return HessianSum()
        method = ipctk.PSDProjectionMethod.CLAMP if project else ipctk.PSDProjectionMethod.NONE
        return SparseHessian(self.potential.hessian(self.tangential, self.scene.mesh, self._v(X), method) / self.dt)


class KinematicPenalty(Term):
    """(w/2) Σ_{i ∈ K} ‖X_i − X̂_i‖² pulling prescribed vertices to their targets X̂_i.

    Used only while the prescribed motion (body, Dirichlet vertices) cannot be applied in one
    collision-free move: the prescribed vertices then become unknowns, CCD limits every Newton
    step, and the barrier pushes the cloth ahead of the body (IPC's treatment of Dirichlet
    boundaries, Li et al. 2020 Sec. 4.5). The weight w = ``unit_weight`` / ĥ² (unit_weight =
    the settings' kinematic_penalty × mean cloth vertex mass, so the term scales with ρ) is
    reset by :meth:`begin_step`; the solver stiffens it within a step when the targets stall.
    """

    parameter = "density"

    def __init__(self, kinematic: np.ndarray, unit_weight: float, n_total: int, h: float):
        self.kinematic = kinematic  # [K] vertex ids
        self.unit_weight = float(unit_weight)
        self.h = float(h)
        self.weight = self.unit_weight / self.h**2
        self.target = None
        self.n_total = n_total

    def begin_step(self, state: StepState):
        self.h = state.h
        self.weight = self.unit_weight / state.h**2
        self.target = state.x_goal[self.kinematic]

    def state_derivative(self, X, d: StepTangent):
        """The targets are prescribed (they do not move with θ); w ∝ 1/ĥ²: −2∇E/ĥ dĥ."""
        if not np.any(d.h):
            return None
        return (-2.0 / self.h * self.gradient(X))[:, None] * d.h[None, :]

    def energy(self, X):
        d = X[self.kinematic] - self.target
        return 0.5 * self.weight * float(np.sum(d * d))

    def gradient(self, X):
        out = np.zeros((self.n_total, 3))
        out[self.kinematic] = self.weight * (X[self.kinematic] - self.target)
        return out.ravel()

    def hessian(self, X, project=True):
        diag = np.zeros((self.n_total, 3))
        diag[self.kinematic] = self.weight
        return Diagonal(diag.ravel())
