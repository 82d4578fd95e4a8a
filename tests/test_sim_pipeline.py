"""The CG preconditioner factorised on a second thread, one Newton iteration behind
(sim.pipeline.PipelinedLinearSolver, SimSettings.factor_thread; docs/simulation.md "Session 37")."""

import numpy as np
import pytest
from test_sim_factorization import cloth_system, needs_mkl
from test_sim_resume import MAT, rising_sphere

from physavatar.sim import SimSettings, simulate
from physavatar.sim.assembly import Factorization
from physavatar.sim.pipeline import PipelinedLinearSolver


@needs_mkl
def test_each_solve_uses_the_last_matrix_factor_made_on_the_worker_with_the_same_bits():
    """Over a step's matrices, solve k's preconditioner is the factor of solve k−1's sparsified
    matrix (made on the worker thread): its solves are the same bits as a factor of that matrix
    made on this thread, and every direction meets its tolerance against a dense solve."""
    asm, _, H_of = cloth_system(8)
    b = np.random.default_rng(3).normal(size=asm.n)
    ls = PipelinedLinearSolver(rtol=1e-10, refresh_cg=10**6, backend="pardiso")
    for step, scales in enumerate(((1.0, 1.1, 1.3, 2.0), (0.5, 0.45, 0.3))):
        ls.mark_stale(keep=False)
        last = None
        for s in scales:
            H = H_of(s)
            x = ls.solve(H, b, asm)
            ref = np.linalg.solve(H.toarray(), b)
            assert np.abs(x - ref).max() <= 1e-8 * np.abs(ref).max()
            P = asm.preconditioner_matrix(H if last is None else last)  # a step's first: its own matrix
            assert np.array_equal(ls.factor_matrix.toarray(), P.toarray())
            assert np.array_equal(ls.factor.solve(b), Factorization(P, "pardiso").solve(b))
            last = H
    assert ls.main_factorizations == 2  # one a step (its first solve); the others on the worker
    assert ls.factorizations == 7


@needs_mkl
def test_a_solve_the_lagged_factor_cannot_do_takes_its_own_matrix_factor():
    """CG that does not converge on the last matrix's factor (a very different matrix) takes the
    worker's factor of its own matrix and converges (no direct solve of H)."""
    asm, _, H_of = cloth_system(8)
    b = np.random.default_rng(4).normal(size=asm.n)
    ls = PipelinedLinearSolver(rtol=1e-10, max_cg=15, refresh_cg=10**6, backend="pardiso")
    ls.solve(H_of(1e4), b, asm)
    H = H_of(30.0)  # (CG on the old factor: 40 iterations; on this matrix's own: 10)
    x = ls.solve(H, b, asm)
    ref = np.linalg.solve(H.toarray(), b)
    assert np.abs(x - ref).max() <= 1e-8 * np.abs(ref).max()
    assert np.array_equal(ls.factor_matrix.toarray(), asm.preconditioner_matrix(H).toarray())
    assert ls.main_factorizations == 1 and ls.factorizations == 3  # the first; the lagged one; its own


@needs_mkl
@pytest.mark.parametrize("integrator", ["euler", "bdf2"])
def test_factor_thread_runs_are_bit_identical_and_reach_the_plain_solvers_states(integrator):
    """A sphere rising into a pinned cloth (PARDISO on the small system): two runs with the
    worker thread are the same bits, and each frame is within the Newton tolerance's reach of
    the plain solver's (tight stopping rule: only the CG path differs)."""
    V, F, seq, BF, pins = rising_sphere()
    kw = dict(integrator=integrator, damping_mass=0.5, linear_solver="pardiso", newton_norm="max", newton_tol=1e-7)
    runs = [simulate(V, F, MAT, seq, BF, pins, None, fps=25.0, settings=SimSettings(factor_thread=t, **kw),
                     max_substeps=4) for t in (True, True, False)]
    assert np.array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])  # another CG path: other bits
    assert np.abs(runs[0] - runs[2]).max() < 1e-6
    assert np.abs(runs[0][-1] - runs[0][0]).max() > 0.02  # the cloth did move


@needs_mkl
def test_a_factor_thread_run_resumes_bit_identical():
    """Interrupted after frame 3 and resumed from its checkpoint: the same bits as the whole run
    (a step's first solve always factorises on the main thread, so no worker state crosses a step)."""
    from test_sim_resume import _interrupted_and_resumed

    V, F, seq, BF, pins = rising_sphere()
    kw = dict(fps=25.0, settings=SimSettings(factor_thread=True, linear_solver="pardiso", damping_mass=0.5),
              max_substeps=4)
    args = (V, F, MAT, seq, BF, pins, None)
    full = simulate(*args, **kw)
    ck, rest = _interrupted_and_resumed(args, kw, 3)
    assert np.array_equal(ck.x, full[3]) and np.array_equal(rest[3:], full[3:])


def test_the_resume_key_keeps_main_s_without_the_thread_and_tells_it_apart_with_it():
    from physavatar.data.sim_frames import run_settings

    assert "factor_thread" not in run_settings(SimSettings())
    assert run_settings(SimSettings(factor_thread=True))["factor_thread"] is True


def test_with_cholespy_factor_thread_is_the_plain_solver_bit_for_bit():
    """A worker's cholespy factorisation does not overlap the main thread: with cholespy (and
    "auto" below PARDISO's size) the setting changes nothing."""
    V, F, seq, BF, pins = rising_sphere()
    runs = [simulate(V, F, MAT, seq, BF, pins, None, fps=25.0, max_substeps=4,
                     settings=SimSettings(factor_thread=t, linear_solver="cholespy", damping_mass=0.5))
            for t in (True, False)]
    assert np.array_equal(runs[0], runs[1])
