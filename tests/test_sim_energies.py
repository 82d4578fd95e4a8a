"""Energies of physavatar.sim against finite differences, ipctk and the plate formula."""

import ipctk
import cloth_grid
import numpy as np
import pytest

from physavatar.sim.energies import (
    Bending, Gravity, Inertia, MassDamping, Membrane, StiffnessDamping, dihedral_angle, dihedral_angle_gradient,
)
from physavatar.sim.mesh import ClothTopology
from physavatar.sim.terms import Diagonal, StepState


def grid(n=4, size=1.0):
    return cloth_grid.grid(n, size)


def dense(h, n):
    if h is None:
        return np.zeros((3 * n, 3 * n))
    if isinstance(h, list):
        return sum(dense(b, n) for b in h)
    if isinstance(h, Diagonal):
        return np.diag(h.values)
    H = np.zeros((3 * n, 3 * n))
    for idx, block in zip(h.index, h.values):
        d = (3 * idx[:, None] + np.arange(3)).ravel()
        H[np.ix_(d, d)] += block
    return H


def fd_check(term, x, eps=1e-6):
    """Relative error of gradient and Hessian against central differences."""
    g = term.gradient(x)
    H = dense(term.hessian(x, project=False), len(x))
    fd_g = np.zeros_like(g)
    fd_H = np.zeros_like(H)
    for i in range(g.size):
        xp = x.ravel().copy(); xp[i] += eps
        xm = x.ravel().copy(); xm[i] -= eps
        xp, xm = xp.reshape(-1, 3), xm.reshape(-1, 3)
        fd_g[i] = (term.energy(xp) - term.energy(xm)) / (2 * eps)
        fd_H[:, i] = (term.gradient(xp) - term.gradient(xm)) / (2 * eps)
    return (np.abs(fd_g - g).max() / np.abs(g).max(), np.abs(fd_H - H).max() / np.abs(H).max())


@pytest.fixture
def cloth():
    V, F = grid(4)
    rng = np.random.default_rng(7)
    topo = ClothTopology.build(V, F)
    x = V + 0.15 * rng.normal(size=V.shape)
    return topo, x, rng


@pytest.mark.parametrize("model", ["stvk", "neohookean"])
def test_membrane_derivatives_match_finite_differences(cloth, model):
    topo, x, _ = cloth
    eg, eh = fd_check(Membrane(topo, 37.0, 0.3, model), x)
    assert eg < 1e-5 and eh < 1e-5


def test_bending_derivatives_match_finite_differences(cloth):
    topo, x, _ = cloth
    eg, eh = fd_check(Bending(topo, 2e-4), x)
    assert eg < 1e-5 and eh < 1e-5


def test_mass_terms_and_damping_derivatives(cloth):
    topo, x, rng = cloth
    free = np.ones(len(x)); free[[0, 5]] = 0.0
    inertia = Inertia(topo, 0.2, 0.04, free)
    inertia.target = x + 0.01 * rng.normal(size=x.shape)
    damp = MassDamping(inertia, 3.0)
    damp.previous = x + 0.02 * rng.normal(size=x.shape)
    stiff = StiffnessDamping(0.01, 0.04, [Membrane(topo, 20.0, 0.2), Bending(topo, 1e-4)])
    stiff.begin_step(StepState.at_rest(x + 0.05 * rng.normal(size=x.shape), 0.04))
    for term in (inertia, damp, stiff):
        eg, eh = fd_check(term, x)
        assert eg < 1e-5 and eh < 1e-5, type(term).__name__
    grav = Gravity(topo, 0.2, free)
    g = grav.gradient(x).reshape(-1, 3)
    # −∇E_gravity is the weight m g of each free vertex; total = ρ · free area · g
    assert np.allclose(-g.sum(0), 0.2 * np.sum(topo.vertex_area * free) * np.array([0, 0, -9.81]))


def test_dihedral_angle_matches_ipctk():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(20, 4, 3))
    ours = dihedral_angle(X)
    ref = np.array([ipctk.dihedral_angle(*X[i]) for i in range(len(X))])
    assert np.allclose(ours, ref, atol=1e-12)
    g = dihedral_angle_gradient(X).reshape(20, 12)
    gref = np.array([ipctk.dihedral_angle_gradient(*X[i]) for i in range(len(X))]).reshape(20, 12)
    assert np.allclose(g, gref, rtol=1e-9, atol=1e-9)


def test_psd_projection_gives_psd_blocks(cloth):
    topo, x, _ = cloth
    for term in (Membrane(topo, 10.0, 0.3), Bending(topo, 1e-3)):
        H = dense(term.hessian(x * np.array([0.6, 0.6, 1.0]), project=True), len(x))
        assert np.linalg.eigvalsh(H).min() > -1e-9 * np.abs(H).max()


def equilateral_sheet(n=24, L=0.02):
    """Equilateral triangle mesh (rows offset by half an edge) in the xy-plane."""
    rows = []
    for j in range(n):
        for i in range(n):
            rows.append([(i + 0.5 * (j % 2)) * L, j * L * np.sqrt(3) / 2, 0.0])
    V = np.array(rows)
    F = []
    for j in range(n - 1):
        for i in range(n - 1):
            a, b, c, d = j * n + i, j * n + i + 1, (j + 1) * n + i, (j + 1) * n + i + 1
            if j % 2 == 0:
                F += [[a, b, c], [b, d, c]]
            else:
                F += [[a, b, d], [a, d, c]]
    return V, np.array(F)


@pytest.mark.parametrize("axis", [0, 1])
def test_bending_stiffness_is_plate_rigidity(axis):
    """Wrapping an equilateral mesh on a cylinder of radius R stores (κb/2)/R² per area."""
    V, F = equilateral_sheet()
    topo = ClothTopology.build(V, F)
    kb, R = 1e-4, 0.5
    s = V[:, axis] - V[:, axis].mean()
    x = V.copy()
    x[:, axis] = R * np.sin(s / R)
    x[:, 2] = R * (1 - np.cos(s / R))
    # interior hinges only: boundary hinges see a truncated dual area
    energy = Bending(topo, kb)
    inner = np.all(np.isin(topo.hinges, np.flatnonzero(
        (np.abs(V[:, 0] - V[:, 0].mean()) < 0.35 * np.ptp(V[:, 0]))
        & (np.abs(V[:, 1] - V[:, 1].mean()) < 0.35 * np.ptp(V[:, 1])))), axis=1)
    X = x[topo.hinges[inner]]
    theta = dihedral_angle(X) - energy.rest_angle[inner]
    e_hinge = kb * energy.weight[inner] * theta**2
    # each interior triangle owns one third of the area of its three hinges' diamonds
    area = np.sum(0.5 * (2 * energy.weight[inner]) ** -1 * np.sum((V[topo.hinges[inner, 1]] - V[topo.hinges[inner, 0]]) ** 2, 1)) / 1.5
    assert np.sum(e_hinge) / area == pytest.approx(0.5 * kb / R**2, rel=0.03)
