"""Terms of the incremental potential of one implicit step (cloth DOFs; the term protocol: terms.py).

    E(x) = ½‖x − x̃‖²_M / ĥ² + gravity + membrane + bending + damping (+ contact, contact.py)

Each term gives ``energy(x)``, ``gradient(x)`` and ``hessian(x, project)`` (the protocol of
ipctk's python/examples/solver.py) and ``begin_step(state)``; the Newton solver only sums them.
``x`` is the stacked positions [N, 3]; gradients are flat [3N] (vertex-major: 3i + k).
Hessians are :class:`~physavatar.sim.terms.Hessian` s (per-element :class:`Blocks`, scattered
into a fixed sparse pattern by :mod:`physavatar.sim.assembly`, or a :class:`Diagonal`).

Every term is linear in one material parameter (``term.parameter`` names it, ``term.scale``
is its value): inertia, gravity and mass damping in ρ, membrane in κs, bending in κb. Hence
∂(∇E)/∂log θ = ∇E_term, and the sensitivity pass (sensitivity.py) needs nothing else.
"""

from __future__ import annotations

import numpy as np

from . import _kernels
from .mesh import ClothTopology
from .terms import Blocks, Diagonal, HessianSum, StepState, StepTangent, Term

GRAVITY = np.array([0.0, 0.0, -9.81])  # DESIGN.md: z up, m/s²


def project_psd(blocks: np.ndarray) -> np.ndarray:
    """Clamp negative eigenvalues of symmetric blocks [M, n, n] to zero (batched eigh).

    Newton needs a positive semi-definite Hessian for a descent direction; projecting each
    element's block keeps the global matrix sparse and PSD (Teran et al. 2005).
    """
    if len(blocks) == 0:
        return blocks
    sym = 0.5 * (blocks + np.swapaxes(blocks, 1, 2))
    w, q = np.linalg.eigh(sym)
    if np.all(w >= 0):
        return sym
    w = np.maximum(w, 0.0)
    return np.einsum("mij,mj,mkj->mik", q, w, q)


# -- inertia and gravity -------------------------------------------------------------------------


class Inertia(Term):
    """½ (x − x̃)ᵀ M (x − x̃) / ĥ² over the free vertices; M = ρ × lumped area (linear in ρ).

    x̃ = X̂ + ĥ V̂ is the step's inertial prediction and ĥ its implicit step (``dt``), both
    from the step's state (:meth:`begin_step`). Dirichlet vertices get no inertia: their
    positions are prescribed, so their mass would only add a constant (or fight the
    prescription while they are penalised, solver.py).
    """

    parameter = "density"

    def __init__(self, topo: ClothTopology, density: float, dt: float, free_mask: np.ndarray):
        self.scale = float(density)
        self.dt = float(dt)
        self.unit_mass = topo.vertex_area * free_mask  # [N] mass per unit density
        self.target = topo.rest.copy()  # x̃, set per step
        self.v_base = np.zeros_like(self.target)

    def begin_step(self, state: StepState):
        self.dt = state.h
        self.v_base = state.v_base
        self.target = state.x_base + state.h * state.v_base

    def state_derivative(self, x, d: StepTangent):
        """∇E = M (x − X̂ − ĥV̂)/ĥ²: −M (dX̂ + ĥ dV̂)/ĥ² − (M V̂/ĥ² + 2M (x − x̃)/ĥ³) dĥ."""
        h = self.dt
        m = np.repeat(self.mass, 3)
        out = -(m / h**2)[:, None] * (d.x_base + h * d.v_base)
        if np.any(d.h):
            dh = -(m / h**2) * self.v_base.ravel() - 2.0 * (m / h**3) * (x - self.target).ravel()
            out += dh[:, None] * d.h[None, :]
        return out

    @property
    def mass(self) -> np.ndarray:
        """[N] lumped vertex masses (kg); zero on Dirichlet vertices."""
        return self.scale * self.unit_mass

    def energy(self, x):
        d = x - self.target
        return 0.5 * np.sum(self.mass[:, None] * d * d) / self.dt**2

    def gradient(self, x):
        return ((self.mass[:, None] / self.dt**2) * (x - self.target)).ravel()

    def hessian(self, x, project=True):
        return Diagonal(np.repeat(self.mass / self.dt**2, 3))


class Gravity(Term):
    """−Σ m_i g·x_i (linear in ρ)."""

    parameter = "density"

    def __init__(self, topo: ClothTopology, density: float, free_mask: np.ndarray, g=GRAVITY):
        self.scale = float(density)
        self.unit_mass = topo.vertex_area * free_mask
        self.g = np.asarray(g, dtype=np.float64)

    def energy(self, x):
        return -self.scale * float(np.sum(self.unit_mass * (x @ self.g)))

    def gradient(self, x):
        return (-self.scale * self.unit_mass[:, None] * self.g[None, :]).ravel()

    def hessian(self, x, project=True):
        return HessianSum()  # linear


class MassDamping(Term):
    """Mass-proportional (Rayleigh α) damping as a potential: α/(2ĥ) ‖x − X̂‖²_M.

    Its gradient α M (x − X̂)/ĥ = α M v is the damping force of the step's velocity, so the
    term is exactly a dissipative potential (linear in ρ, scales with mass). X̂ (``previous``)
    and ĥ come from the step's state.
    """

    parameter = "density"

    def __init__(self, inertia: Inertia, alpha: float):
        self.inertia = inertia
        self.alpha = float(alpha)
        self.h = inertia.dt
        self.previous = inertia.target.copy()  # X̂, set per step

    @property
    def scale(self):
        return self.inertia.scale

    def begin_step(self, state: StepState):
        self.h = state.h
        self.previous = state.x_base

    def state_derivative(self, x, d: StepTangent):
        """∇E = αM (x − X̂)/ĥ: −αM dX̂/ĥ − αM (x − X̂) dĥ/ĥ²."""
        m = np.repeat(self.inertia.mass, 3)
        out = -(self.alpha * m / self.h)[:, None] * d.x_base
        if np.any(d.h):
            out -= ((self.alpha * m / self.h**2) * (x - self.previous).ravel())[:, None] * d.h[None, :]
        return out

    def _w(self):
        return self.alpha * self.inertia.mass / self.h

    def energy(self, x):
        d = x - self.previous
        return 0.5 * np.sum(self._w()[:, None] * d * d)

    def gradient(self, x):
        return (self._w()[:, None] * (x - self.previous)).ravel()

    def hessian(self, x, project=True):
        return Diagonal(np.repeat(self._w(), 3))


class StiffnessDamping(Term):
    """Stiffness-proportional (Rayleigh β) damping: β/(2ĥ) (x − xₜ)ᵀ K(xₜ) (x − xₜ).

    K(xₜ) is the PSD-projected elastic Hessian at the start of the step (lagged, as friction
    is), so the term is a fixed quadratic per step; it depends on κs and κb through K (not
    linearly on one parameter, and on xₜ through K: no exact sensitivities).
    """

    parameter = ("stretch_stiffness", "bend_stiffness")

    def __init__(self, beta: float, dt: float, elastic_terms):
        self.beta = float(beta)
        self.dt = float(dt)
        self.elastic_terms = elastic_terms
        self.previous = None
        self.blocks: list[Blocks] = []

    def begin_step(self, state: StepState):
        x_prev = state.x_prev
        self.dt = state.h
        self.previous = x_prev.copy()
        c = self.beta / self.dt
        self.blocks = []
        for term in self.elastic_terms:
            # "eigen": K(xₜ) is the eigenvalue-clamped Hessian whatever PSD approximation the
            # Newton solver uses, so the damping model does not depend on a solver setting.
            b = term.hessian(x_prev, project="eigen")
            self.blocks.append(Blocks(b.index, c * b.values))

    def _matvec(self, d):
        out = np.zeros_like(d)
        for b in self.blocks:
            k = b.index.shape[1]
            local = d[b.index].reshape(len(b.index), 3 * k)
            f = np.einsum("mij,mj->mi", b.values, local).reshape(-1, 3)
            np.add.at(out, b.index.ravel(), f)
        return out

    def energy(self, x):
        d = x - self.previous
        return 0.5 * float(np.sum(d * self._matvec(d)))

    def gradient(self, x):
        return self._matvec(x - self.previous).ravel()

    def hessian(self, x, project=True):
        return HessianSum(self.blocks)


# -- membrane ------------------------------------------------------------------------------------

# δF basis: the 6 unit directions of a 3×2 deformation gradient, index 2i + j.
_DF_BASIS = np.zeros((6, 3, 2))
for _i in range(3):
    for _j in range(2):
        _DF_BASIS[2 * _i + _j, _i, _j] = 1.0


class Membrane(Term):
    """Isotropic membrane energy Σ_t A_t W(F_t) of linear triangles (plane stress).

    F [3, 2] maps the 2D rest frame to world, C = FᵀF. With κs = Young's modulus × thickness
    and Poisson ratio ν: μ = κs / (2(1 + ν)), λ = κs ν / (1 − ν²) (plane-stress Lamé), so W and
    everything below is linear in κs.

    - ``"stvk"`` (the paper): W = μ ‖E‖² + λ/2 tr(E)², E = (C − I)/2.
    - ``"neohookean"`` (Codim-IPC's default): W = μ/2 (tr C − 2) − μ ln J + λ/2 (ln J)²,
      J = √det C.

    The Hessian is built in F-space (6×6 per triangle, PSD-projected there, which is cheaper
    than projecting the 9×9 and still makes the 9×9 = Gᵀ K G PSD), then mapped to vertices.
    """

    parameter = "stretch_stiffness"

    def __init__(self, topo: ClothTopology, stretch_stiffness: float, poisson: float, model="stvk"):
        if model not in ("stvk", "neohookean"):
            raise ValueError(f"membrane model must be 'stvk' or 'neohookean', got {model!r}")
        self.topo = topo
        self.scale = float(stretch_stiffness)
        self.poisson = float(poisson)
        self.model = model
        self.index = topo.faces
        self.area = topo.face_area
        self.G = topo.face_grad  # [F, 3, 2]

    @property
    def lame(self):
        nu = self.poisson
        return self.scale / (2.0 * (1.0 + nu)), self.scale * nu / (1.0 - nu * nu)

    def deformation_gradient(self, x):
        """F: [F, 3, 2]."""
        return np.einsum("fai,faj->fij", x[self.index], self.G)

    def _density(self, F):
        """Energy density W [F], second Piola stress S [F, 2, 2] and helpers."""
        mu, lam = self.lame
        C = np.einsum("fki,fkj->fij", F, F)
        if self.model == "stvk":
            E = 0.5 * (C - np.eye(2))
            trE = E[:, 0, 0] + E[:, 1, 1]
            W = mu * np.einsum("fij,fij->f", E, E) + 0.5 * lam * trE**2
            S = 2.0 * mu * E + lam * trE[:, None, None] * np.eye(2)
            return W, S, C, None
        det = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] * C[:, 1, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            logJ = 0.5 * np.log(det)
            Cinv = np.stack(
                [np.stack([C[:, 1, 1], -C[:, 0, 1]], -1), np.stack([-C[:, 1, 0], C[:, 0, 0]], -1)],
                axis=1,
            ) / det[:, None, None]
        trC = C[:, 0, 0] + C[:, 1, 1]
        W = 0.5 * mu * (trC - 2.0) - mu * logJ + 0.5 * lam * logJ**2
        S = mu * (np.eye(2) - Cinv) + lam * logJ[:, None, None] * Cinv
        return W, S, C, (logJ, Cinv)

    def energy(self, x):
        """Ψ (numba kernel; :meth:`energy_numpy` is its reference twin)."""
        args = self._kernel_args(x)
        total = float(_kernels.membrane_energy(*args))
        return total if np.isfinite(total) else np.inf

    def energy_numpy(self, x):
        W, _, _, _ = self._density(self.deformation_gradient(x))
        total = float(np.sum(self.area * W))
        return total if np.isfinite(total) else np.inf  # collapsed triangle (Neo-Hookean)

    def _kernel_args(self, x):
        mu, lam = self.lame
        model = _kernels.MODEL_STVK if self.model == "stvk" else _kernels.MODEL_NEOHOOKEAN
        return (np.ascontiguousarray(x, dtype=np.float64), self.index, self.G, self.area, mu, lam, model)

    def gradient(self, x):
        """∇Ψ [3N] (numba kernel; :meth:`gradient_numpy` is its reference twin)."""
        return _kernels.membrane_gradient(*self._kernel_args(x), len(x)).ravel()

    def hessian(self, x, project=True):
        """Blocks [F, 9, 9] (numba kernel; :meth:`hessian_numpy` is its reference twin)."""
        return Blocks(self.index, _kernels.membrane_hessian(*self._kernel_args(x), bool(project)))

    def gradient_numpy(self, x):
        F = self.deformation_gradient(x)
        _, S, _, _ = self._density(F)
        P = np.einsum("fij,fjk->fik", F, S)  # first Piola stress [F, 3, 2]
        g = self.area[:, None, None] * np.einsum("fij,faj->fai", P, self.G)  # [F, 3 verts, 3]
        out = np.zeros((len(x), 3))
        np.add.at(out, self.index.ravel(), g.reshape(-1, 3))
        return out.ravel()

    def stress_hessian(self, x):
        """∂²W/∂F² [F, 6, 6] (vec F index 2i + j), from δP = δF S + F δS."""
        F = self.deformation_gradient(x)
        _, S, C, extra = self._density(F)
        mu, lam = self.lame
        dF = _DF_BASIS  # [6, 3, 2]
        FtdF = np.einsum("fki,bkj->fbij", F, dF)  # Fᵀ δF
        dC = FtdF + np.swapaxes(FtdF, 2, 3)
        if self.model == "stvk":
            trdC = dC[:, :, 0, 0] + dC[:, :, 1, 1]
            dS = mu * dC + 0.5 * lam * trdC[:, :, None, None] * np.eye(2)
        else:
            logJ, Cinv = extra
            CdC = np.einsum("fij,fbjk,fkl->fbil", Cinv, dC, Cinv)
            tr = np.einsum("fij,fbji->fb", Cinv, dC)
            dS = (mu - lam * logJ)[:, None, None, None] * CdC + 0.5 * lam * tr[
                :, :, None, None
            ] * Cinv[:, None]
        dP = np.einsum("bij,fjk->fbik", dF, S) + np.einsum("fij,fbjk->fbik", F, dS)
        K = dP.reshape(len(F), 6, 6)
        return 0.5 * (K + np.swapaxes(K, 1, 2))

    def hessian_numpy(self, x, project=True):
        K = self.stress_hessian(x)
        if project:
            K = project_psd(K)
        K = K.reshape(-1, 3, 2, 3, 2)
        H = self.area[:, None, None, None, None] * np.einsum(
            "faj,fijkl,fbl->faibk", self.G, K, self.G
        )
        return Blocks(self.index, H.reshape(-1, 9, 9))


# -- bending -------------------------------------------------------------------------------------


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def dihedral_angle(X):
    """Signed hinge angle θ [H] of hinges X [H, 4, 3] (same convention as ipctk.dihedral_angle)."""
    x0, x1, x2, x3 = X[:, 0], X[:, 1], X[:, 2], X[:, 3]
    e = x1 - x0
    nA = np.cross(e, x2 - x0)
    nB = np.cross(x3 - x0, e)
    e_hat = e / np.linalg.norm(e, axis=1)[:, None]
    return np.arctan2(_dot(np.cross(nA, nB), e_hat), _dot(nA, nB))


def dihedral_angle_gradient(X):
    """∂θ/∂X [H, 4, 3] in closed form (Bridson et al. 2003; Tamstorf & Grinspun 2013).

    Written with algebraic operations only (no abs, no conjugation), so it is complex-analytic
    and its complex-step derivative is the exact Hessian (see :func:`dihedral_angle_hessian`).
    """
    x0, x1, x2, x3 = X[:, 0], X[:, 1], X[:, 2], X[:, 3]
    e = x1 - x0
    n1 = np.cross(x2 - x0, x2 - x1)
    n2 = np.cross(x3 - x1, x3 - x0)
    le = np.sqrt(_dot(e, e))
    n1 = n1 / _dot(n1, n1)[:, None]
    n2 = n2 / _dot(n2, n2)[:, None]
    g2 = -le[:, None] * n1
    g3 = -le[:, None] * n2
    g0 = -(_dot(x2 - x1, e) / le)[:, None] * n1 - (_dot(x3 - x1, e) / le)[:, None] * n2
    g1 = (_dot(x2 - x0, e) / le)[:, None] * n1 + (_dot(x3 - x0, e) / le)[:, None] * n2
    return np.stack([g0, g1, g2, g3], axis=1)


_COMPLEX_STEP = 1e-30


def dihedral_angle_hessian(X):
    """∂²θ/∂X² [H, 12, 12] by complex-step differentiation of the closed-form gradient.

    Im(∇θ(X + i s e_j)) / s is ∂(∇θ)/∂X_j with no subtractive cancellation, so with
    s = 1e-30 the result is exact to rounding (Squire & Trapp 1998) — no hand-expanded
    12×12 formula to get wrong, and vectorised over all hinges (12 gradient evaluations).
    """
    n = len(X)
    flat = X.reshape(n, 12).astype(np.complex128)
    H = np.empty((n, 12, 12))
    for j in range(12):
        flat[:, j] += 1j * _COMPLEX_STEP
        H[:, :, j] = dihedral_angle_gradient(flat.reshape(n, 4, 3)).reshape(n, 12).imag / _COMPLEX_STEP
        flat[:, j] -= 1j * _COMPLEX_STEP
    return 0.5 * (H + np.swapaxes(H, 1, 2))


class Bending(Term):
    """Discrete-shell hinge bending (Grinspun et al. 2003): Σ_e (κb/2) w_e (θ_e − θ̄_e)².

    w_e = ‖ē‖² / Ā_e with ē the rest edge and Ā_e the summed rest area of its two triangles
    (the ‖ē‖/h̄_e weight of Discrete Shells with h̄_e = Ā_e/(3‖ē‖), divided by 3). With the
    factor ½ this makes κb the flexural rigidity D [N·m]: an equilateral mesh wrapped on a
    cylinder of curvature k stores (κb/2) k² per unit area, the Kirchhoff plate energy
    (tests/test_sim_energies.py measures it; on a finite mesh the chord of an edge running
    along the curvature also folds its hinge, which is why the factor is ½ and not the 3/2 a
    smooth-normal argument suggests). Grinspun's coefficient k in k Σ 3‖ē‖²/Ā_e θ² is thus
    κb/6. θ̄ is the rest mesh's angle (curved garments keep their shape).
    """

    parameter = "bend_stiffness"

    def __init__(self, topo: ClothTopology, bend_stiffness: float):
        self.scale = float(bend_stiffness)
        self.index = topo.hinges
        X = topo.rest[self.index]
        length2 = np.sum((X[:, 1] - X[:, 0]) ** 2, axis=1)
        area = 0.5 * (
            np.linalg.norm(np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), axis=1)
            + np.linalg.norm(np.cross(X[:, 1] - X[:, 0], X[:, 3] - X[:, 0]), axis=1)
        )
        self.weight = 0.5 * length2 / area  # the ½ of (κb/2) is kept in the weight
        self.rest_angle = dihedral_angle(X)
        # PSD approximation used when hessian(project=True): the exact per-hinge eigenvalue
        # clamp by default; the solver picks SimSettings.bending_hessian.
        self.projection = "eigen"

    def energy(self, x):
        """Ψ (numba kernel; :meth:`energy_numpy` is its reference twin)."""
        if len(self.index) == 0:
            return 0.0
        x = np.ascontiguousarray(x, dtype=np.float64)
        return float(_kernels.bending_energy(x, self.index, self.weight, self.rest_angle, self.scale))

    def energy_numpy(self, x):
        if len(self.index) == 0:
            return 0.0
        d = dihedral_angle(x[self.index]) - self.rest_angle
        return float(self.scale * np.sum(self.weight * d * d))

    def gradient(self, x):
        """∇Ψ [3N] (numba kernel; :meth:`gradient_numpy` is its reference twin)."""
        if len(self.index) == 0:
            return np.zeros(3 * len(x))
        x = np.ascontiguousarray(x, dtype=np.float64)
        return _kernels.bending_gradient(x, self.index, self.weight, self.rest_angle, self.scale,
                                         len(x)).ravel()

    def hessian(self, x, project=True):
        """Blocks [H, 12, 12] (numba kernel; :meth:`hessian_numpy` is its reference twin).

        project: False = exact; "eigen" = eigenvalues clamped at 0; "gauss_newton" = the
        ∇θ∇θᵀ part only (PSD by construction); True = ``self.projection`` (the solver's choice,
        SimSettings.bending_hessian).
        """
        if project is True:
            project = self.projection
        mode = {False: _kernels.BENDING_EXACT, "eigen": _kernels.BENDING_EIGEN,
                "gauss_newton": _kernels.BENDING_GAUSS_NEWTON}[project]
        x = np.ascontiguousarray(x, dtype=np.float64)
        H = _kernels.bending_hessian(x, self.index, self.weight, self.rest_angle, self.scale, mode)
        return Blocks(self.index, H)

    def gradient_numpy(self, x):
        out = np.zeros((len(x), 3))
        if len(self.index) == 0:
            return out.ravel()
        X = x[self.index]
        d = dihedral_angle(X) - self.rest_angle
        g = (2.0 * self.scale * self.weight * d)[:, None, None] * dihedral_angle_gradient(X)
        np.add.at(out, self.index.ravel(), g.reshape(-1, 3))
        return out.ravel()

    def hessian_numpy(self, x, project=True):
        """Reference twin of :meth:`hessian` (project: False, True/"eigen", "gauss_newton")."""
        X = x[self.index]
        d = dihedral_angle(X) - self.rest_angle
        g = dihedral_angle_gradient(X).reshape(-1, 12)
        c = 2.0 * self.scale * self.weight
        gg = np.einsum("hi,hj->hij", g, g)
        if project == "gauss_newton":
            return Blocks(self.index, c[:, None, None] * gg)
        H = c[:, None, None] * (gg + d[:, None, None] * dihedral_angle_hessian(X))
        if project:
            H = project_psd(H)
        return Blocks(self.index, H)
