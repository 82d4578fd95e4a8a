"""Forward sensitivities of a simulation with respect to material parameters (exact gradients).

The solution x⁺ of one step satisfies ∇E(x⁺; s, θ) = 0, s the step's state (its base X̂, V̂
and implicit step ĥ: terms.StepState) and θ the parameters. Differentiating,

    H ∂x⁺ = −( ∂∇E/∂log θ + ∂∇E/∂s · ∂s ),    ∂v⁺ = (∂x⁺ − ∂x̂)/ĥ − (x⁺ − x̂) ∂ĥ/ĥ²,

with H the exact (unprojected) Hessian at the solution over the free DOFs. Both right-hand
parts come from the terms' protocol (terms.py), so a new term needs no edit here:

- ∂∇E/∂log θ = Σ ∇E_term over the terms whose declared ``parameter`` is θ (each is linear in
  it);
- ∂∇E/∂s · ∂s = Σ ``term.state_derivative(X, tangent)``, the tangent ∂s being the sensitivity
  of the step's base (xₜ, vₜ for implicit Euler; for BDF2 x̂ = (1 + γ/3) xₜ − γ/3 xₜ₋₁ and v̂
  likewise, ClothSim.step_base).

The one parameter that is not a term's is the integrator's BDF2 blend γ (Material.bdf2_blend):
it moves the base (x̂, v̂ above) and ĥ = (1 − γ/3) h. Dirichlet vertices and the body are
prescribed: zero sensitivity (the body's base moves with ĥ so that its velocity does not).
Friction's lagged normal forces and tangent bases are held fixed, as the solver does within a
step, and the adaptive barrier stiffness is taken ∝ ρ (its declared parameter); docs/physics.md
"Exact gradients" says what that leaves out.

H need not be positive definite (folds, the barrier's curvature left unresolved by the Newton
tolerance), so it is not factorised: GMRES on H, preconditioned with the Cholesky factors of the
PSD-projected Newton matrix the step already has (:func:`_solve_exact`).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from .material import Material
from .settings import SimSettings
from .solver import ClothSim
from .terms import StepTangent, differentiable

BLEND = "bdf2_blend"  # the integrator's parameter (ClothSim.step_base), not a term's


@dataclasses.dataclass
class Rollout:
    """One simulated window.

    positions: [T, N, 3]; jacobian: [T, N, 3, P] ∂x_t/∂log θ_p (None unless requested);
    newton_iterations: total over the steps; converged: every step met the Newton tolerance.
    """

    positions: np.ndarray
    jacobian: np.ndarray | None
    newton_iterations: int
    converged: bool
    wall_time: float


def _solve_exact(H: sp.csr_matrix, rhs: np.ndarray, preconditioners=(), rtol: float = 1e-10) -> np.ndarray:
    """Solve H S = rhs [n, P] with the exact (unprojected) Hessian H at the step's solution.

    H need not be positive definite: near a buckling minimiser (folds, the barrier's curvature
    left unresolved by the Newton tolerance) it has small negative eigenvalues, and a
    Cholesky of H fails (CHOLMOD "not positive definite") while a pivoting LU of a 10⁴-DOF
    shell Hessian takes seconds per step. So H is not factorised: GMRES (indefinite-safe) runs
    on H, preconditioned with a Cholesky factor of the PSD-projected Newton matrix the step
    already has (it differs from H only in the clamped negative curvature of membrane, bending
    and contact, so tens of iterations suffice). ``preconditioners``: callables, each returning
    a solve ([n] -> [n]) or None, tried in order until GMRES reaches ``rtol``; LU is the
    always-right last resort.
    """
    rhs = np.asarray(rhs, dtype=np.float64)
    for make in preconditioners:
        solve = make()
        if solve is None:
            continue
        M = sla.LinearOperator(H.shape, matvec=solve, dtype=np.float64)
        X = np.zeros_like(rhs)
        ok = True
        for j in range(rhs.shape[1]):
            b = rhs[:, j]
            bn = np.linalg.norm(b)
            if bn == 0.0:
                continue
            x, info = sla.gmres(H, b, x0=solve(b), M=M, rtol=rtol, atol=0.0, restart=50, maxiter=4)
            res = np.linalg.norm(H @ x - b) / bn
            if not (np.isfinite(res) and res <= 10 * rtol):
                ok = False
                break
            X[:, j] = x
        if ok:
            return X
    return sla.splu(H.tocsc()).solve(rhs)


def check_parameters(sim: ClothSim, names) -> None:
    """Raise ValueError unless every name is a parameter some active term of ``sim`` declares
    (or the BDF2 blend) and every active term can be differentiated (terms.differentiable)."""
    terms = sim.active_terms()
    declared = sorted({t.parameter for t in terms if isinstance(getattr(t, "parameter", None), str)})
    unknown = set(names) - set(declared) - {BLEND}
    if unknown:
        raise ValueError(f"unknown parameters {sorted(unknown)}; choose from {tuple(declared) + (BLEND,)}")
    for t in terms:
        why = differentiable(t)
        if why:
            raise ValueError(f"no exact sensitivities: {why}")


def step_sensitivity(sim: ClothSim, X, S, V, names, dh=None):
    """Propagate (S, V) [3N, P] = ∂(x̂, v̂)/∂log θ of the base of the step ``sim`` just took
    (xₜ, vₜ for implicit Euler) through it; X [N + Nb, 3] is the step's solution (cloth, then
    the body at its pose). ``dh`` [P]: ∂ĥ/∂θ of each column (nonzero only for the BDF2 blend).
    Returns (S, V) of the step's result (module docstring)."""
    n = sim.n
    state = sim.step_state
    h = state.h
    P = len(names)
    dh = np.zeros(P) if dh is None else np.asarray(dh, dtype=np.float64)
    D = X.size
    dX = np.zeros((D, P))
    dV = np.zeros((D, P))
    dX[: 3 * n], dV[: 3 * n] = S, V
    if np.any(dh):  # the body's base bt + (1 − ĥ/h)(bt1 − bt) moves with ĥ, its velocity does not
        move = ((state.x_goal[n:] - state.x_prev[n:]) / state.dt).ravel()
        dX[3 * n:] = -move[:, None] * dh[None, :]
    tangent = StepTangent(dX, dV, dh)
    terms = sim.active_terms()
    H, dof_map = sim.exact_hessian(X)
    fidx = np.flatnonzero(dof_map[: 3 * n] >= 0)
    order = dof_map[fidx]  # reduced row of each free cloth DOF
    coupling = np.zeros((D, P))  # ∂∇E/∂s · ∂s
    for t in terms:
        c = t.state_derivative(X, tangent)
        if c is not None:
            coupling += c
    rhs = np.zeros((len(fidx), P))
    for j, name in enumerate(names):  # ∂∇E/∂log θ: the gradients of the terms linear in θ
        own = [t.gradient(X) for t in terms if getattr(t, "parameter", None) == name]
        g = np.sum(own, axis=0) if own else np.zeros(D)
        rhs[order, j] = -(g[: 3 * n][fidx] + coupling[fidx, j])
    sol = _solve_exact(H, rhs, sim.linearization.preconditioners(H.shape[0]))
    S_new = np.zeros_like(S)
    S_new[fidx] = sol[order]
    V_new = (S_new - S) / h
    for j in np.flatnonzero(dh):  # v⁺ = (x⁺ − x̂)/ĥ moves with ĥ too
        V_new[:, j] -= (X[:n] - state.x_base[:n]).ravel() * (dh[j] / h**2)
    return S_new, V_new


def rollout(garment_rest, faces, material: Material, collider_sequence, collider_faces, boundary_indices,
            boundary_targets, fps: float = 25.0, substeps: int = 1, settings: SimSettings | None = None,
            x0=None, parameters=None, extra_terms=()) -> Rollout:
    """Simulate from ``x0`` (default the rest shape) at rest, with the sensitivities of every
    frame with respect to ``parameters`` (in log space; the BDF2 blend as is). Returns a
    :class:`Rollout`.

    Args:
        garment_rest: [N, 3] rest shape; faces: [F, 3].
        collider_sequence: [T, Nb, 3] body per frame, or None (no body); collider_faces: [Fb, 3].
        boundary_indices: [K] Dirichlet vertices; boundary_targets: [T, K, 3] their positions
            per frame (T frames are simulated; K may be 0).
        fps: frames per second; substeps: implicit steps per frame (body and targets
            interpolated linearly).
        settings: :class:`SimSettings` (dt is set from fps and substeps; default SimSettings()).
        parameters: names of parameters the active terms declare (``term.parameter``) or
            ``"bdf2_blend"``; None or () for a plain simulation.
        extra_terms: further terms of E (ClothSim).
    """
    t0 = time.perf_counter()
    settings = settings or SimSettings()
    h = 1.0 / (fps * substeps)
    names = tuple(parameters or ())
    want = bool(names)
    settings = dataclasses.replace(settings, dt=h, keep_linearization=want or settings.keep_linearization)
    sim = ClothSim(garment_rest, faces, material, settings, boundary_indices, extra_terms=extra_terms)
    tg = np.asarray(boundary_targets, dtype=np.float64)
    bodies = collider_sequence
    T, N = len(tg), len(garment_rest)

    def body(f, w):  # the body a fraction w into frame f's move (f ≥ 1), or None
        return None if bodies is None else (1 - w) * bodies[f - 1] + w * bodies[f]

    if want:
        sim.prepare(body(1, 0.0), collider_faces)
        check_parameters(sim, names)
    x = np.array(garment_rest if x0 is None else x0, dtype=np.float64)
    v = np.zeros_like(x)
    out = np.empty((T, N, 3))
    out[0] = x
    P = len(names)
    S = np.zeros((3 * N, P))  # ∂x_t/∂log θ (flat, vertex-major)
    V = np.zeros((3 * N, P))
    bdf2 = settings.integrator == "bdf2"
    g3 = material.bdf2_blend / 3.0  # the base's weight on xₜ₋₁ (ClothSim.step_base)
    jb = names.index(BLEND) if BLEND in names else None
    history = None  # (x, v, S, V) at t−1 (BDF2)
    jac = np.zeros((T, N, 3, P)) if want else None
    iters, converged = 0, True
    for f in range(1, T):
        for k in range(substeps):
            w0, w1 = k / substeps, (k + 1) / substeps
            b0, b1 = body(f, w0), body(f, w1)
            target = (1 - w1) * tg[f - 1] + w1 * tg[f] if len(sim.boundary) else None
            dh = np.zeros(P)  # ∂ĥ/∂θ: −h/3 for γ on a BDF2 step with history
            if bdf2 and history is not None:  # the base of the step and its sensitivities
                xp, vp, Sp, Vp = history
                SB, VB = (1.0 + g3) * S - g3 * Sp, (1.0 + g3) * V - g3 * Vp
                if jb is not None:  # x̂ = (1 + γ/3) xₜ − γ/3 xₜ₋₁ moves with γ itself
                    SB[:, jb] += (x - xp).ravel() / 3.0
                    VB[:, jb] += (v - vp).ravel() / 3.0
                    dh[jb] = -h / 3.0
                history = (x, v, S, V)
                x, v, st = sim.step(x, v, b0, b1, collider_faces, target, history=(xp, vp))
            else:  # implicit Euler (BDF2's first step too)
                history = (x, v, S, V)
                SB, VB = S, V
                x, v, st = sim.step(x, v, b0, b1, collider_faces, target)
            iters += st.newton_iterations
            converged &= st.converged
            if not np.all(np.isfinite(x)):
                raise FloatingPointError("simulation produced non-finite positions")
            if want:
                X = x if b1 is None else np.vstack([x, b1])
                S, V = step_sensitivity(sim, X, SB, VB, names, dh)
        out[f] = x
        if want:
            jac[f] = S.reshape(N, 3, P)
    return Rollout(out, jac, iters, converged, time.perf_counter() - t0)
