"""The numba kernels and the CG linear solver of physavatar.sim against their numpy twins."""

import cloth_grid
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from physavatar.sim.assembly import Assembler, NewtonLinearSolver, pcg, unique_int
from physavatar.sim.energies import Bending, Membrane
from physavatar.sim.terms import Diagonal
from physavatar.sim.mesh import ClothTopology


def grid(n=5, size=1.0):
    return cloth_grid.grid(n, size)


@pytest.fixture
def cloth():
    V, F = grid()
    topo = ClothTopology.build(V, F)
    rng = np.random.default_rng(11)
    # compressed in-plane and crumpled: membrane and hinge blocks both get negative eigenvalues
    x = V * np.array([0.7, 0.8, 1.0]) + 0.1 * rng.normal(size=V.shape)
    return topo, x


def close(a, b, rtol=1e-10):
    return np.abs(a - b).max() <= rtol * max(np.abs(b).max(), 1e-300)


@pytest.mark.parametrize("model", ["stvk", "neohookean"])
def test_membrane_kernels_match_numpy(cloth, model):
    topo, x = cloth
    m = Membrane(topo, 37.0, 0.3, model)
    assert abs(m.energy(x) - m.energy_numpy(x)) <= 1e-12 * abs(m.energy_numpy(x))
    assert close(m.gradient(x), m.gradient_numpy(x))
    for project in (False, True):
        assert close(m.hessian(x, project).values, m.hessian_numpy(x, project).values, 1e-9)
    # the eigenvalue clamp did act on this state (otherwise the projection is untested)
    assert not close(m.hessian(x, True).values, m.hessian(x, False).values)


@pytest.mark.parametrize("model", ["stvk", "neohookean"])
def test_membrane_closed_form_projection_equals_eigendecomposition(model):
    """The singular-frame 2×2-block clamp (_kernels._project_psd_isotropic) gives the same
    matrix as clamping the 6×6 eigendecomposition, in uniaxial / biaxial compression, near-
    equal singular values (s₁ ≈ s₂: the frame is then arbitrary) and mixed stretch."""
    from physavatar.sim import _kernels

    V, F = grid(4)
    topo = ClothTopology.build(V, F)
    m = Membrane(topo, 37.0, 0.3, model)
    rng = np.random.default_rng(5)
    Q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    for stretch in ([0.7, 0.8, 1.0], [0.9, 0.9, 1.0], [1.2, 0.6, 1.0], [0.95, 0.95 + 1e-9, 1.0]):
        for noise in (0.0, 0.05):
            x = (V * np.array(stretch) + noise * rng.normal(size=V.shape)) @ Q.T
            args = m._kernel_args(x)
            fast = _kernels.membrane_hessian(*args, True)
            ref = _kernels.membrane_hessian(*args, 3)  # eigendecomposition clamp
            assert close(fast, ref, 1e-10), (stretch, noise)
            assert close(fast, m.hessian_numpy(x, True).values, 1e-10)
            # flipped ("abs") eigenvalues: the block route against an explicit eigh
            K = m.stress_hessian(x)
            w, q = np.linalg.eigh(K)
            K_abs = np.einsum("mij,mj,mkj->mik", q, np.abs(w), q).reshape(-1, 3, 2, 3, 2)
            H_abs = m.area[:, None, None, None, None] * np.einsum("faj,fijkl,fbl->faibk", m.G, K_abs, m.G)
            assert close(_kernels.membrane_hessian(*args, 2), H_abs.reshape(-1, 9, 9), 1e-10)


@pytest.mark.parametrize("model", ["stvk", "neohookean"])
def test_element_kernels_give_each_element_the_bits_of_its_own_call(cloth, model):
    """The kernels keep their per-element scratch arrays across the loop (allocated once):
    each element's block is the same bits as the kernel run on that element alone, so nothing
    leaks from one element into the next. Mixed states: the closed-form clamp, the eigh
    fallback (a collapsed triangle) and unprojected blocks all occur."""
    from physavatar.sim import _kernels

    topo, x = cloth
    x = x.copy()
    a, b, c = topo.faces[3]
    x[c] = 0.5 * (x[a] + x[b]) + 1e-5  # a sliver (s₂ ≪ s₁): the eigh fallback
    m = Membrane(topo, 37.0, 0.3, model)
    x_, tri, G, area, mu, lam, mdl = m._kernel_args(x)
    Fd = np.einsum("ai,aj->ij", x_[tri[3]], G[3])
    e = np.linalg.eigvalsh(Fd.T @ Fd)
    assert e[0] < 1e-6 * e[1]  # the sliver takes the eigh fallback of the closed-form clamp
    for project in (False, True, 2):  # 2: flipped eigenvalues
        batch = _kernels.membrane_hessian(x_, tri, G, area, mu, lam, mdl, project)
        for f in range(len(tri)):
            one = _kernels.membrane_hessian(x_, tri[f:f + 1], G[f:f + 1], area[f:f + 1], mu, lam, mdl, project)
            assert np.array_equal(batch[f], one[0]), (project, f)
    g = _kernels.membrane_gradient(x_, tri, G, area, mu, lam, mdl, len(x_))
    g1 = sum(_kernels.membrane_gradient(x_, tri[f:f + 1], G[f:f + 1], area[f:f + 1], mu, lam, mdl, len(x_))
             for f in range(len(tri)))
    assert close(g, g1, 1e-14)  # summed in another order: per-element blocks checked above
    b = Bending(topo, 2e-4)
    for mode in ("gauss_newton", "eigen", False):
        batch = b.hessian(x, mode).values
        for h in range(len(b.index)):
            one = _kernels.bending_hessian(x, b.index[h:h + 1], b.weight[h:h + 1], b.rest_angle[h:h + 1], b.scale,
                                           _kernels_mode(mode))
            assert np.array_equal(batch[h], one[0]), (mode, h)


def _kernels_mode(mode):
    from physavatar.sim import _kernels

    return {"gauss_newton": _kernels.BENDING_GAUSS_NEWTON, "eigen": _kernels.BENDING_EIGEN,
            False: _kernels.BENDING_EXACT}[mode]


def test_neohookean_energy_kernel_is_inf_on_inverted_triangles(cloth):
    topo, x = cloth
    m = Membrane(topo, 37.0, 0.3, "neohookean")
    flat = x.copy()
    flat[topo.faces[0]] = flat[topo.faces[0][0]]  # a collapsed triangle (det C = 0)
    assert m.energy(flat) == np.inf and m.energy_numpy(flat) == np.inf


def test_bending_kernels_match_numpy(cloth):
    topo, x = cloth
    b = Bending(topo, 2e-4)
    assert abs(b.energy(x) - b.energy_numpy(x)) <= 1e-12 * abs(b.energy_numpy(x))
    assert close(b.gradient(x), b.gradient_numpy(x))
    for project in (False, "eigen", "gauss_newton"):
        assert close(b.hessian(x, project).values, b.hessian_numpy(x, project).values, 1e-9), project
    b.projection = "gauss_newton"
    assert close(b.hessian(x, True).values, b.hessian_numpy(x, "gauss_newton").values)
    for project in ("eigen", "gauss_newton"):
        w = np.linalg.eigvalsh(b.hessian(x, project).values)
        assert w.min() > -1e-12 * np.abs(w).max()


def test_assembly_matches_numpy_twin(cloth):
    topo, x = cloth
    n = len(x)
    dof_map = np.arange(3 * n)
    dof_map[:6] = -1  # two eliminated vertices
    dof_map[6:] = np.arange(3 * n - 6)
    asm = Assembler(dof_map, [topo.faces, topo.hinges], topo.hinges[:, 2:])
    m, b = Membrane(topo, 20.0, 0.2), Bending(topo, 1e-3)
    diag = Diagonal(np.linspace(1.0, 2.0, 3 * n))
    e = topo.edges[5]  # a contact-like block on an edge: inside the pattern
    d = (3 * e[:, None] + np.arange(3)).ravel()
    rng = np.random.default_rng(0)
    block = rng.normal(size=(6, 6))
    inside = sp.coo_matrix((block.ravel(), (np.repeat(d, 6), np.tile(d, 6))), shape=(3 * n, 3 * n))
    far = np.array([2, n - 1])  # two vertices sharing no element: outside the pattern
    d2 = (3 * far[:, None] + np.arange(3)).ravel()
    outside = sp.coo_matrix((block.ravel(), (np.repeat(d2, 6), np.tile(d2, 6))), shape=(3 * n, 3 * n))
    for extra in ([inside], [outside], [inside, outside]):
        hs = [m.hessian(x), b.hessian(x), diag] + extra
        A, B = asm.assemble(hs), asm.assemble_numpy(hs)
        assert abs(A - B).max() <= 1e-12 * abs(B).max()
    assert asm.assemble([m.hessian(x), inside]).nnz == asm.nnz  # pattern kept
    for M in (inside, outside, inside + outside):  # numba slot search == the numpy twin
        (s1, v1), (s2, v2) = asm._sparse_slots(M), asm._sparse_slots_numpy(M)
        assert (s1 is None) == (s2 is None) and (s1 is None or (np.array_equal(s1, s2) and np.array_equal(v1, v2)))
    assert asm._sparse_slots(outside)[0] is None and asm._sparse_slots(inside)[0] is not None
    # the pattern and scatter map of the setup (numba kernels) against their numpy twins: a
    # permuted reduced numbering (not in vertex order) with single eliminated DOFs too
    perm = np.random.default_rng(7).permutation(3 * n)
    for dm in (dof_map, np.where(np.arange(3 * n) % 7 == 3, -1, perm)):
        dm = dm.copy()
        kept = dm >= 0
        dm[kept] = np.argsort(np.argsort(dm[kept]))  # 0..n_kept-1
        a2 = Assembler(dm, [topo.faces, topo.hinges], topo.hinges[:, 2:])
        keys = np.unique(np.concatenate([np.arange(a2.n) * (a2.n + 1)]
                                        + [a2._element_keys_numpy(i) for i in (topo.faces, topo.hinges)]))
        assert np.array_equal(a2.keys, keys)
        for index in (topo.faces, topo.hinges):
            assert np.array_equal(a2.scatter[id(index)], a2._element_slots_numpy(index))
    with pytest.raises(IndexError, match="DOF map"):
        Assembler(np.arange(9), [np.array([[0, 1, 3]])])


def test_cg_solver_matches_direct_solve(cloth):
    topo, x = cloth
    n = len(x)
    asm = Assembler(np.arange(3 * n), [topo.faces, topo.hinges], topo.hinges[:, 2:])
    hs = [Membrane(topo, 20.0, 0.2).hessian(x), Bending(topo, 1e-2).hessian(x, "gauss_newton"),
          Diagonal(np.full(3 * n, 0.5))]
    H = asm.assemble(hs)
    P = asm.preconditioner_matrix(H)
    assert P.nnz < H.nnz  # hinge-tip couplings dropped
    P_coo = asm._preconditioner_matrix_coo(H)  # the twin (any pattern) gives the same bits
    assert np.array_equal(P.indptr, P_coo.indptr) and np.array_equal(P.indices, P_coo.indices)
    assert np.array_equal(P.data, P_coo.data)
    assert np.linalg.eigvalsh((P - H).toarray()).min() > -1e-10 * abs(H).max()  # P ⪰ H
    b = np.random.default_rng(1).normal(size=3 * n)
    ref = sla.spsolve(H.tocsc(), b)
    solver = NewtonLinearSolver(rtol=1e-10)
    for scale in (1.0, 1.1, 3.0):  # reused factor, then one that no longer fits
        Hs = asm.assemble(hs[:2] + [Diagonal(np.full(3 * n, 0.5 * scale))])
        xs = solver.solve(Hs, b, asm)
        assert np.linalg.norm(Hs @ xs - b) <= 1e-9 * np.linalg.norm(b)
    assert np.allclose(NewtonLinearSolver(max_cg=0).solve(H, b, asm), ref, rtol=1e-8, atol=1e-12)
    xs, its, ok = pcg(H, b, lambda r: r / H.diagonal(), 1e-8, 1000)
    assert ok and np.allclose(xs, ref, rtol=1e-6, atol=1e-9)


def test_unique_int_is_np_unique():
    """The Assembler's pattern keys are made unique by sorting (faster than numpy 2.4's hashing)."""
    rng = np.random.default_rng(3)
    for a in (rng.integers(-50, 10**9, 20_000), rng.integers(0, 30, (40, 7)), np.zeros(0, np.int64)):
        out = unique_int(a)
        assert out.dtype == a.dtype and np.array_equal(out, np.unique(a))


def test_bending_kernels_leave_out_a_hinge_whose_triangle_has_no_area(cloth):
    """Three vertices of a triangle on one line (sim.untangle can put them on a body edge): the
    dihedral angle of its hinges is 0/0. The kernels used to stop with ZeroDivisionError; they
    now leave those hinges out, and the rest equals the numpy twin on the other hinges."""
    import copy

    topo, x = cloth
    b = Bending(topo, 2e-4)
    f = topo.faces[7]
    x = x.copy()
    x[f[2]] = x[f[0]] + 0.37 * (x[f[1]] - x[f[0]])  # on the line of the other two, not on either
    u, w = x[f[1]] - x[f[0]], x[f[2]] - x[f[0]]
    assert np.linalg.norm(np.cross(u, w)) < 1e-14 * np.linalg.norm(u) * np.linalg.norm(w)  # rounding only
    bad = np.array([len(set(f) & set(h[:3])) == 3 or len(set(f) & {h[0], h[1], h[3]}) == 3 for h in b.index])
    assert 1 <= bad.sum() <= 3
    ref = copy.copy(b)
    ref.index, ref.weight, ref.rest_angle = b.index[~bad], b.weight[~bad], b.rest_angle[~bad]
    assert abs(b.energy(x) - ref.energy_numpy(x)) <= 1e-12 * abs(ref.energy_numpy(x))
    assert close(b.gradient(x), ref.gradient_numpy(x))
    for project in (False, "eigen", "gauss_newton"):
        H = b.hessian(x, project).values
        assert np.all(H[bad] == 0.0)
        assert close(H[~bad], ref.hessian_numpy(x, project).values, 1e-9), project
