"""The sensitivity pass works from the term protocol alone (physavatar.sim.terms): terms written
here, with parameters no material has and a dependence on the step's state, get exact
sensitivities (against central finite differences of the simulator) with no edit to physavatar."""

import dataclasses

import cloth_grid
import numpy as np
import pytest

from physavatar.sim import SimSettings, preset
from physavatar.sim.energies import project_psd
from physavatar.sim.sensitivity import rollout
from physavatar.sim.terms import Blocks, Diagonal, StepState, Term

TIGHT = SimSettings(newton_tol=1e-6)


class Springs(Term):
    """(k/2) Σ_e (|x_i − x_j| − L_e)² over the cloth edges: linear in k ("spring_stiffness"), its
    Hessian in blocks over an element set the assembler was not built with."""

    parameter = "spring_stiffness"

    def __init__(self, rest, faces, k):
        e = np.sort(np.vstack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        self.index = np.unique(e, axis=0)
        self.rest = np.linalg.norm(rest[self.index[:, 0]] - rest[self.index[:, 1]], axis=1)
        self.scale = float(k)

    def _d(self, x):
        d = x[self.index[:, 0]] - x[self.index[:, 1]]
        return d, np.linalg.norm(d, axis=1)

    def energy(self, x):
        _, length = self._d(x)
        return 0.5 * self.scale * float(np.sum((length - self.rest) ** 2))

    def gradient(self, x):
        d, length = self._d(x)
        f = (self.scale * (length - self.rest) / length)[:, None] * d
        out = np.zeros_like(x)
        np.add.at(out, self.index[:, 0], f)
        np.add.at(out, self.index[:, 1], -f)
        return out.ravel()

    def hessian(self, x, project=True):
        d, length = self._d(x)
        u = d / length[:, None]
        uu = np.einsum("ei,ej->eij", u, u)
        K = self.scale * (uu + ((length - self.rest) / length)[:, None, None] * (np.eye(3) - uu))
        H = np.block([[K, -K], [-K, K]])
        return Blocks(self.index, project_psd(H) if project else H)


class Drag(Term):
    """(c/2ĥ) Σ_i a_i ‖x_i − X̂_i‖² over the cloth vertices: linear in c ("drag"), and reading the
    step's base X̂ and implicit step ĥ (begin_step), so it gives their derivative."""

    parameter = "drag"

    def __init__(self, area, c):
        self.area = np.asarray(area, dtype=np.float64)
        self.scale = float(c)

    def begin_step(self, state: StepState):
        self.base, self.h = state.x_base, state.h

    def _w(self, n):  # [n] weight per row (the body's rows: 0)
        w = np.zeros(n)
        w[: len(self.area)] = self.scale * self.area / self.h
        return w

    def energy(self, x):
        d = x - self.base
        return 0.5 * float(np.sum(self._w(len(x))[:, None] * d * d))

    def gradient(self, x):
        return (self._w(len(x))[:, None] * (x - self.base)).ravel()

    def hessian(self, x, project=True):
        return Diagonal(np.repeat(self._w(len(x)), 3))

    def state_derivative(self, x, d):
        w = np.repeat(self._w(len(x)), 3)
        return -w[:, None] * d.x_base - (w * (x - self.base).ravel() / self.h)[:, None] * d.h[None, :]


def hanging_cloth(frames=7, seed=0):
    """A 6×6 cloth (30 cm) pinned along one edge, swinging down under gravity from a slightly
    rippled rest shape, and a noisy reference around rest."""
    V, F = cloth_grid.grid(6, 0.3)
    rng = np.random.default_rng(seed)
    V[:, 2] += 0.003 * rng.standard_normal(len(V))
    ref = np.repeat(V[None], frames, 0) + 0.01 * rng.standard_normal((frames, len(V), 3))
    pins = np.arange(6)
    return V, F, pins, ref


def vertex_area(V, F):
    a = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    out = np.zeros(len(V))
    np.add.at(out, F.ravel(), np.repeat(a / 3.0, 3))
    return out


def loss_and_gradient(material, settings, k, c, names):
    V, F, pins, ref = hanging_cloth()
    terms = [Springs(V, F, k), Drag(vertex_area(V, F), c)]
    r = rollout(V, F, material, None, None, pins, ref[:, pins], 25.0, settings=settings, parameters=names,
                extra_terms=terms)
    res = (r.positions - ref)[1:]
    grad = None if r.jacobian is None else 2.0 * r.jacobian[1:].reshape(-1, len(names)).T @ res.reshape(-1)
    return float(np.sum(res * res)), grad, r


def central_fd(material, settings, k, c, names, eps):
    """∂L/∂log θ (∂L/∂γ for the BDF2 blend) by central differences of the simulator."""
    out = []
    for n in names:
        args = []
        for sign in (1.0, -1.0):
            m, kk, cc = material, k, c
            if n == "spring_stiffness":
                kk = k * np.exp(sign * eps)
            elif n == "drag":
                cc = c * np.exp(sign * eps)
            elif n == "bdf2_blend":
                m = dataclasses.replace(material, bdf2_blend=material.bdf2_blend + sign * eps)
            else:
                m = dataclasses.replace(material, **{n: getattr(material, n) * np.exp(sign * eps)})
            args.append(loss_and_gradient(m, settings, kk, cc, ())[0])
        out.append((args[0] - args[1]) / (2 * eps))
    return np.array(out)


@pytest.mark.parametrize("integrator", ["euler", "bdf2"])
def test_new_terms_get_exact_sensitivities_from_their_declared_parameters(integrator):
    m = dataclasses.replace(preset("cotton"), integrator=integrator, bdf2_blend=0.6)
    k, c = 2.0, 0.5 * m.density
    if integrator == "euler":
        names, settings, eps = ("spring_stiffness", "drag", "stretch_stiffness"), TIGHT, 1e-4
    else:  # the blend moves the step's base and ĥ: the drag's state_derivative carries both
        names = ("spring_stiffness", "drag", "bdf2_blend")
        settings, eps = dataclasses.replace(TIGHT, integrator="bdf2", newton_tol=1e-7), 1e-3
    _, exact, r = loss_and_gradient(m, settings, k, c, names)
    assert r.converged
    fd = central_fd(m, settings, k, c, names, eps)
    assert np.all(np.abs(fd) > 1e-5), fd  # every parameter matters: the check is not vacuous
    np.testing.assert_array_less(np.abs(exact - fd) / np.abs(fd), 1e-3)


def test_terms_the_pass_cannot_differentiate_are_refused():
    class Lagged(Drag):  # reads the step's state but gives no derivative of it
        state_derivative = Term.state_derivative

    V, F, pins, ref = hanging_cloth(frames=3)
    run = lambda names, terms=(): rollout(V, F, preset("cotton"), None, None, pins, ref[:, pins],  # noqa: E731
                                          parameters=names, extra_terms=terms)
    with pytest.raises(ValueError, match="unknown parameters"):
        run(("drag",))
    with pytest.raises(ValueError, match="no state_derivative"):
        run(("density",), [Lagged(vertex_area(V, F), 0.1)])
    with pytest.raises(ValueError, match="not linearly on one parameter"):
        rollout(V, F, preset("cotton"), None, None, pins, ref[:, pins], settings=SimSettings(damping_stiffness=0.01),
                parameters=("density",))
    assert run(()).jacobian is None  # a plain simulation needs no differentiable terms
