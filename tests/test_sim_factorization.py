"""The sparse Cholesky backends of physavatar.sim (cholespy, MKL PARDISO) against a dense solve,
and the Newton linear solver on each of them against the other."""

import cloth_grid
import numpy as np
import pytest
import scipy.sparse as sp

from physavatar.sim import assembly, pardiso
from physavatar.sim.assembly import Assembler, Factorization, NewtonLinearSolver
from physavatar.sim.energies import Bending, Membrane
from physavatar.sim.mesh import ClothTopology
from physavatar.sim.terms import Diagonal

needs_mkl = pytest.mark.skipif(not pardiso.available(), reason="MKL (the optional 'mkl' extra) not installed")


def cloth_system(n=6, shift=0.5):
    """A cloth Newton system: membrane + Gauss–Newton hinges + a mass diagonal, its assembler."""
    V, F = cloth_grid.grid(n, 1.0)
    topo = ClothTopology.build(V, F)
    x = V + np.random.default_rng(0).normal(scale=0.02, size=V.shape)
    nv = len(V)
    asm = Assembler(np.arange(3 * nv), [topo.faces, topo.hinges], topo.hinges[:, 2:])
    hs = [Membrane(topo, 20.0, 0.2).hessian(x), Bending(topo, 1e-2).hessian(x, "gauss_newton")]
    return asm, hs, (lambda s: asm.assemble(hs + [Diagonal(np.full(3 * nv, shift * s))]))


@needs_mkl
def test_pardiso_factor_solves_like_a_dense_solve():
    asm, _, H_of = cloth_system()
    rng = np.random.default_rng(1)
    B = rng.normal(size=(asm.n, 3))
    f = Factorization(H_of(1.0), "pardiso")
    assert f.backend == "pardiso"
    assert Factorization(H_of(1.0), "auto").backend == "cholespy"  # "auto": small systems keep cholespy
    for k, s in enumerate((1.0, 1.3, 7.0)):
        H = H_of(s)
        # the same pattern: the numeric phase on f's handle (move), or a new handle with f's ordering
        g = Factorization(H, "pardiso", f, move=k % 2 == 0) if k else f
        ref = np.linalg.solve(H.toarray(), B)
        assert np.abs(g.solve(B[:, 0]) - ref[:, 0]).max() <= 1e-10 * np.abs(ref).max()
        assert np.abs(g.solve(B) - ref).max() <= 1e-10 * np.abs(ref).max()  # several right-hand sides
        if k and k % 2 == 0:
            with pytest.raises(RuntimeError, match="moved"):
                f.solve(B[:, 0])  # its handle went to g
        f = g
    # another pattern (the preconditioner's): a fresh analysis, still exact
    P = asm.preconditioner_matrix(H_of(1.0))
    g = Factorization(P, "pardiso", f, move=True)
    assert np.allclose(g.solve(B[:, 1]), np.linalg.solve(P.toarray(), B[:, 1]), rtol=1e-10, atol=1e-14)
    assert np.allclose(f.solve(B[:, 1]), np.linalg.solve(H_of(7.0).toarray(), B[:, 1]), rtol=1e-10, atol=1e-14)


@needs_mkl
def test_pardiso_factor_of_a_fixed_pattern_gathers_the_upper_triangle_like_triu():
    """A matrix on the pattern arrays of the last factor's (the Newton solver's fixed patterns)
    takes its upper triangle by a kept gather: the same values, pattern and factor bits as
    scipy's triu of a copy (the general path), moved or not."""
    asm, _, H_of = cloth_system(6)
    b = np.random.default_rng(4).normal(size=asm.n)
    f = pardiso.PardisoCholesky(H_of(1.0))
    for move in (False, True):
        H = H_of(1.7 if move else 1.3)  # assembled on the assembler's own index arrays
        g = pardiso.PardisoCholesky(H, f, move=move)
        assert g._upper is f._upper  # the gather path
        U = sp.triu(H, format="csr")
        Hc = sp.csr_matrix((H.data.copy(), H.indices.copy(), H.indptr.copy()), shape=H.shape)
        ref = pardiso.PardisoCholesky(Hc, pardiso.PardisoCholesky(Hc))  # new arrays: triu, the same ordering
        assert ref._upper is not f._upper
        for a in (g, ref):
            assert np.array_equal(a.indptr, U.indptr) and np.array_equal(a.indices, U.indices)
            assert np.array_equal(a.data, U.data)  # the same values in the same order, no arithmetic
        assert np.array_equal(g.solve(b), ref.solve(b))  # bit-identical factors
        assert np.abs(g.solve(b) - np.linalg.solve(H.toarray(), b)).max() <= 1e-10 * np.abs(g.solve(b)).max()
        f = g
    # a matrix with duplicate entries (not canonical) still takes scipy's triu + sum_duplicates
    H = H_of(1.0)
    k = H.indptr[1]  # a second (0, 0) entry at the end of row 0
    D = sp.csr_matrix((np.insert(H.data, k, 0.5), np.insert(H.indices, k, 0), np.r_[0, H.indptr[1:] + 1]), shape=H.shape)
    assert not D.has_canonical_format
    d = pardiso.PardisoCholesky(D)
    assert d._upper is None and np.allclose(d.solve(b), np.linalg.solve(D.toarray(), b), rtol=1e-10)


@needs_mkl
def test_pardiso_falls_back_to_lu_on_an_indefinite_matrix():
    A = sp.csr_matrix(np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.5], [0.0, 0.5, 3.0]]))  # eigenvalues of both signs
    f = Factorization(A, "pardiso")
    assert f.backend == "lu"
    b = np.array([1.0, -2.0, 0.5])
    assert np.allclose(f.solve(b), np.linalg.solve(A.toarray(), b), rtol=1e-12)


@needs_mkl
def test_newton_linear_solver_gives_the_same_directions_on_both_backends():
    """The preconditioned CG of the Newton solver, cholespy against PARDISO, over several
    matrices (the factor reused, refreshed in place, then a new step): each to its tolerance."""
    asm, _, H_of = cloth_system(8)
    b = np.random.default_rng(2).normal(size=asm.n)
    solvers = {k: NewtonLinearSolver(rtol=1e-10, refresh_cg=20, backend=k) for k in ("cholespy", "pardiso")}
    for s in (1.0, 1.1, 3.0, 0.2, 0.21):
        if s == 0.2:
            for ls in solvers.values():
                ls.mark_stale()
        H = H_of(s)
        x = {k: ls.solve(H, b, asm) for k, ls in solvers.items()}
        ref = np.linalg.solve(H.toarray(), b)
        for v in x.values():
            assert np.abs(v - ref).max() <= 1e-8 * np.abs(ref).max()
    assert solvers["pardiso"].factor.backend == "pardiso" and solvers["cholespy"].factor.backend == "cholespy"
    assert solvers["pardiso"].factorizations == solvers["cholespy"].factorizations  # the same refresh decisions


def test_without_mkl_auto_is_cholespy_and_pardiso_says_what_is_missing(monkeypatch):
    monkeypatch.setattr(pardiso, "_LIB", False)  # as if the mkl extra were not installed
    asm, _, H_of = cloth_system(4)
    H = H_of(1.0)
    b = np.ones(asm.n)
    f = Factorization(H, "auto")
    assert f.backend == "cholespy"
    assert np.allclose(f.solve(b), np.linalg.solve(H.toarray(), b), rtol=1e-10)
    with pytest.raises(ValueError, match="mkl"):
        Factorization(H, "pardiso")
    with pytest.raises(ValueError, match="backend"):
        Factorization(H, "umfpack")


def test_unknown_linear_solver_setting_is_one_clear_error():
    from physavatar.sim import ClothSim, SimSettings, preset

    V, F = cloth_grid.grid(3, 1.0)
    with pytest.raises(ValueError, match="linear_solver"):
        ClothSim(V, F, preset("cotton"), SimSettings(linear_solver="mumps"))


@pytest.mark.parametrize("backend", ["cholespy", pytest.param("pardiso", marks=needs_mkl)])
def test_full_preconditioner_is_the_newton_matrix_and_auto_picks_it_by_size(backend, monkeypatch):
    asm, _, H_of = cloth_system(6)
    b = np.random.default_rng(3).normal(size=asm.n)
    H = H_of(1.0)
    ref = np.linalg.solve(H.toarray(), b)
    full = NewtonLinearSolver(rtol=1e-10, backend=backend, preconditioner="full")
    x = full.solve(H, b, asm)
    assert full.cg_iterations == 0 and full.factor_matrix is H  # a fresh factor of H: exact at once
    assert np.abs(x - ref).max() <= 1e-10 * np.abs(ref).max()
    H2 = H_of(1.05)  # the next iteration: the aged factor preconditions CG
    x2 = full.solve(H2, b, asm)
    assert full.factorizations == 1 and 0 < full.cg_iterations <= 20
    assert np.abs(x2 - np.linalg.solve(H2.toarray(), b)).max() <= 1e-8 * np.abs(ref).max()
    auto = NewtonLinearSolver(backend=backend)
    assert auto._preconditioner_matrix(H, asm).nnz < H.nnz  # small system: the sparsified matrix
    monkeypatch.setattr(NewtonLinearSolver, "FULL_MIN_ROWS", asm.n)
    monkeypatch.setattr(assembly, "PARDISO_MIN_ROWS", asm.n)
    assert (auto._preconditioner_matrix(H, asm) is H) == (backend == "pardiso")  # full only with PARDISO


@needs_mkl
def test_a_new_step_without_kept_linearization_refactorises_in_place_to_the_same_bits():
    """mark_stale(keep=False): the next step's first factor takes over the old PARDISO handle
    (numeric phase only) instead of a new analysis; the directions are the same bits."""
    asm, _, H_of = cloth_system(8)
    b = np.random.default_rng(5).normal(size=asm.n)
    solvers = {keep: NewtonLinearSolver(backend="pardiso") for keep in (True, False)}
    for step in range(3):
        old = {}
        for keep, ls in solvers.items():
            old[keep] = ls.factor
            ls.mark_stale(keep=keep)
        for s in (1.0 + step, 1.05 + step):
            x = {keep: ls.solve(H_of(s), b, asm) for keep, ls in solvers.items()}
            assert np.array_equal(x[True], x[False])
        if step:
            assert np.array_equal(old[True].solve(b), old[True].solve(b))  # kept: still solves
            with pytest.raises(RuntimeError, match="moved"):
                old[False].solve(b)  # its handle went to this step's factor
    assert solvers[True].factorizations == solvers[False].factorizations
