"""The term protocol: what every term of a step's incremental potential E provides.

The Newton solver (solver.py) and the sensitivity pass (sensitivity.py) only ever talk to terms
through this protocol, so a new term (an energy, a constraint penalty) is one class:

- ``energy(X) -> float``, ``gradient(X) -> [3n]``, ``hessian(X, project) -> Hessian`` of the
  stacked positions X [n, 3] (cloth rows, then body rows; flat vectors are vertex-major,
  3i + k). ``project=True`` asks for a positive semi-definite approximation (Newton), False
  for the exact Hessian (sensitivities).
- ``parameter``: the one material parameter θ the term is *linear* in (E_term ∝ θ), or None.
  Then ∂∇E_term/∂log θ = ∇E_term, which is all the sensitivity pass needs; a term that depends
  on a parameter in any other way declares a tuple of names and is refused by it.
- ``begin_step(state)``: called by the solver once per step, before anything is evaluated, with
  the step's :class:`StepState` (its base, implicit step, prescribed positions). A term that
  reads the state there also gives ``state_derivative(X, tangent)``: ∂∇E/∂(state) along a
  :class:`StepTangent`, the coupling of one step to the last in the sensitivities.

:class:`Term` is a base with the defaults (no parameter, no state). Hessians come in one type,
:class:`Hessian`, in the forms the assembler (assembly.py) scatters fastest: per-element dense
:class:`Blocks`, a :class:`Diagonal`, a :class:`SparseHessian` (ipctk's contact Hessians) and a
:class:`HessianSum` of those.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp

# -- the step's state ----------------------------------------------------------------------------


@dataclasses.dataclass
class StepState:
    """What one implicit step starts from (ClothSim hands it to every term's ``begin_step``).

    All positions are stacked [cloth (n); body (nb)] rows, [n + nb, 3].

    Attributes:
        x_prev: positions at t (the body where the last step left it).
        x_base: the step's base X̂: implicit Euler xₜ, BDF2 4/3 xₜ − 1/3 xₜ₋₁ (ClothSim.step_base);
            the body at the matching constant-velocity base, so that its velocity
            (X − X̂)/ĥ is its move over the step, (body_{t+1} − body_t)/dt, whatever ĥ.
        v_base: the base velocity V̂ (cloth; the body's move over the step / dt). The inertial
            prediction is x̃ = X̂ + ĥ V̂.
        x_goal: the prescribed positions at t+1 (the body's pose, the Dirichlet vertices'
            targets); the free cloth rows are x_prev's.
        h: the implicit step ĥ (dt for implicit Euler, (1 − γ/3) dt for BDF2).
        dt: the step's length.
    """

    x_prev: np.ndarray
    x_base: np.ndarray
    v_base: np.ndarray
    x_goal: np.ndarray
    h: float
    dt: float

    @classmethod
    def at_rest(cls, x, h: float) -> "StepState":
        """A step from rest at x [n, 3] (nothing prescribed): for terms used on their own."""
        x = np.asarray(x, dtype=np.float64)
        return cls(x, x, np.zeros_like(x), x, float(h), float(h))


@dataclasses.dataclass
class StepTangent:
    """P directions of change of a :class:`StepState` at once (the sensitivity pass's columns).

    x_base, v_base: [3(n + nb), P] changes of X̂ and V̂; h: [P] changes of ĥ. x_prev and the
    prescribed positions are inputs of the step that do not move with the parameters."""

    x_base: np.ndarray
    v_base: np.ndarray
    h: np.ndarray


# -- Hessians ------------------------------------------------------------------------------------


class Hessian:
    """A term's Hessian: a symmetric matrix over the DOFs of the term's X (3 per row).

    Concrete forms: :class:`Blocks`, :class:`Diagonal`, :class:`SparseHessian`, :class:`HessianSum`.
    """

    def parts(self) -> list["Hessian"]:
        """The forms this Hessian is a sum of (itself unless it is a :class:`HessianSum`)."""
        return [self]

    def to_sparse(self, n_dofs: int) -> sp.spmatrix:
        """This Hessian as a scipy sparse matrix [n_dofs, n_dofs] (any format)."""
        raise NotImplementedError

    def dot(self, d: np.ndarray) -> np.ndarray:
        """H d for d [D] or [D, P] (D = the DOFs of the X it was evaluated at)."""
        return self.to_sparse(len(d)) @ d


@dataclasses.dataclass
class Blocks(Hessian):
    """Per-element Hessian blocks: ``values`` [M, 3k, 3k] over vertices ``index`` [M, k]."""

    index: np.ndarray
    values: np.ndarray

    def to_sparse(self, n_dofs):
        k = self.index.shape[1]
        dofs = (3 * self.index[:, :, None] + np.arange(3)).reshape(len(self.index), 3 * k)
        r = np.broadcast_to(dofs[:, :, None], self.values.shape).ravel()
        c = np.broadcast_to(dofs[:, None, :], self.values.shape).ravel()
        return sp.csr_matrix((self.values.ravel(), (r, c)), shape=(n_dofs, n_dofs))


@dataclasses.dataclass
class Diagonal(Hessian):
    """A diagonal Hessian: ``values`` [3n]."""

    values: np.ndarray

    def to_sparse(self, n_dofs):
        v = np.zeros(n_dofs)
        v[: len(self.values)] = self.values
        return sp.diags(v).tocsr()

    def dot(self, d):
        d = np.asarray(d)
        out = np.zeros_like(d, dtype=np.float64)
        m = len(self.values)
        out[:m] = self.values.reshape((m,) + (1,) * (d.ndim - 1)) * d[:m]
        return out


@dataclasses.dataclass
class SparseHessian(Hessian):
    """A sparse Hessian over all DOFs (scipy; ipctk's contact Hessians)."""

    matrix: sp.spmatrix

    def to_sparse(self, n_dofs):
        return self.matrix

    def dot(self, d):
        return self.matrix @ d


class HessianSum(Hessian, list):
    """A sum of Hessians (a list of them); empty = zero (a linear term's Hessian)."""

    def parts(self):
        return [p for h in self for p in h.parts()]

    def to_sparse(self, n_dofs):
        out = sp.csr_matrix((n_dofs, n_dofs))
        for p in self.parts():
            out = out + p.to_sparse(n_dofs)
        return out

    def dot(self, d):
        out = np.zeros_like(np.asarray(d), dtype=np.float64)
        for p in self.parts():
            out += p.dot(d)
        return out


def as_hessian(h) -> Hessian:
    """A :class:`Hessian` from a Hessian, a scipy sparse matrix (over all DOFs), a list of those
    or None (zero)."""
    if isinstance(h, Hessian):
        return h
    if h is None:
        return HessianSum()
    if isinstance(h, list):
        return HessianSum(as_hessian(p) for p in h)
    if sp.issparse(h):
        return SparseHessian(h)
    raise TypeError(f"not a Hessian: {type(h).__name__}")


# -- the term base -------------------------------------------------------------------------------


class Term:
    """Base of the terms of E with the protocol's defaults (module docstring): no parameter,
    independent of the step's state. Subclasses give energy, gradient and hessian."""

    parameter: str | tuple | None = None

    def begin_step(self, state: StepState) -> None:
        """Called once per step with the step's state (default: the term does not use it)."""

    def state_derivative(self, X, tangent: StepTangent) -> np.ndarray | None:
        """∂∇E/∂(step state) along ``tangent``: [3n, P], or None when the term does not depend
        on the state. A term that reads the state in ``begin_step`` must override this."""
        return None

    def energy(self, X) -> float:
        raise NotImplementedError

    def gradient(self, X) -> np.ndarray:
        raise NotImplementedError

    def hessian(self, X, project=True) -> Hessian:
        raise NotImplementedError


def differentiable(term) -> str | None:
    """Why the sensitivity pass cannot differentiate ``term`` (None if it can): a parameter that
    is not a single linear one, or a step state read in ``begin_step`` without a
    ``state_derivative``."""
    p = getattr(term, "parameter", None)
    if p is not None and not isinstance(p, str):
        return f"{type(term).__name__} depends on {p} (not linearly on one parameter)"
    cls = type(term)
    begin = getattr(cls, "begin_step", Term.begin_step)
    deriv = getattr(cls, "state_derivative", Term.state_derivative)
    if begin is not Term.begin_step and deriv is Term.state_derivative:
        return f"{cls.__name__} reads the step's state (begin_step) but gives no state_derivative"
    return None
