"""The CG preconditioner factorised on a second thread, one Newton iteration behind.

:class:`~physavatar.sim.assembly.NewtonLinearSolver` factorises its preconditioner (the
sparsified Newton matrix, or the Newton matrix itself on large systems) on the main thread,
whenever CG needed more than ``refresh_cg`` iterations on the aged factor. MKL PARDISO's
factorisation is a ctypes call, which releases the GIL, so it can run beside the rest of a
Newton iteration (CG, CCD, line search, the next assembly) on the machine's second core.

:class:`PipelinedLinearSolver` does that with a fixed schedule, so that a run does not depend
on how the threads are scheduled: the direction of Newton iteration k is solved by CG
preconditioned with the factor of iteration k − 1's matrix, which a worker thread started
factorising when iteration k − 1's solve began; iteration k waits for it if it is not done,
and starts the factorisation of its own matrix. A step's first solve factorises its matrix on
the main thread (as the plain solver does), and so does a solve whose CG does not converge on
the lagged factor (it then takes the worker's factor of the same matrix: the same bits). Which
factor a solve uses thus depends on the iteration count only, and the factors are PARDISO's on
one thread (bit-identical on repeats): the same bits run to run, whatever the load
(docs/simulation.md "Session 37").

Two PARDISO handles take turns (the factor in use, and the one being made), each refactorising
in place with the first factor's ordering (no symbolic analysis after the first). Where the
factor is cholespy's (``linear_solver`` "cholespy", or "auto" below ``PARDISO_MIN_ROWS`` rows) the
solves are the plain solver's, bit for bit: a worker's cholespy factorisation did not overlap the
main thread (the motion suite's 4-cm dress ran 1.2–1.4× slower with it).
"""

from __future__ import annotations

import threading

from .assembly import Factorization, NewtonLinearSolver, uses_pardiso


class _Job:
    """One factorisation of ``assembler``'s preconditioner matrix of H on a worker thread."""

    def __init__(self, solver: "PipelinedLinearSolver", H, assembler, reuse, move: bool):
        self.result = self.matrix = self.error = None

        def run():
            try:
                M = solver._preconditioner_matrix(H, assembler)
                self.result = Factorization(M, solver.backend, reuse, move=move, threads=solver.threads)
                self.matrix = M
            except BaseException as e:  # noqa: BLE001 - re-raised on the main thread (take)
                self.error = e

        self.thread = threading.Thread(target=run, name="physavatar-factor", daemon=True)
        self.thread.start()

    def take(self):
        self.thread.join()
        if self.error is not None:
            raise self.error
        return self.result, self.matrix


class PipelinedLinearSolver(NewtonLinearSolver):
    """NewtonLinearSolver whose preconditioner is refactorised on a worker thread for every
    solve and used by the next one (module docstring). Same arguments; ``factorizations``
    counts the worker's factorisations too (``main_factorizations``: those on the caller's
    thread)."""

    def __init__(self, *args, **kwargs):
        self._job = None
        self._spare = None  # a factor no solve uses any more: the next job takes over its handle
        self.main_factorizations = 0
        super().__init__(*args, **kwargs)

    def reset(self):
        self._settle()
        self._spare = None
        super().reset()

    def mark_stale(self, keep: bool = True):
        self._settle()
        super().mark_stale(keep)

    def _settle(self):
        """Wait for the running job; its factor's handle becomes the spare."""
        job, self._job = self._job, None
        if job is not None:
            try:
                f, _ = job.take()
            except Exception:  # noqa: BLE001 - an unused factor: its failure does not matter
                f = None
            if f is not None:
                self._spare = f

    def _refactor(self, M):
        super()._refactor(M)
        self.main_factorizations += 1

    def _launch(self, H, assembler):
        spare, self._spare = self._spare, None
        if spare is not None and getattr(spare, "_pardiso", None) is not None and spare.n == H.shape[0]:
            self._job = _Job(self, H, assembler, spare, move=True)
        else:  # a new handle with the factor's ordering (no METIS run)
            self._job = _Job(self, H, assembler, self.factor, move=False)

    def _swap_in(self, f, M):
        self._spare, self.factor = self.factor, f
        self.factor_matrix = M
        self._given = False
        self.factorizations += 1

    def solve(self, H, b, assembler=None, rtol=None):
        if self.max_cg <= 0 or assembler is None or not uses_pardiso(self.backend, H.shape[0]):
            return super().solve(H, b, assembler, rtol)  # (cholespy: the plain solver's bits)
        rtol = self.rtol if rtol is None else max(float(rtol), self.rtol)
        if self.factor is None or self._stale or self.factor.n != H.shape[0]:
            self._settle()
            self._refactor(self._preconditioner_matrix(H, assembler))
            self._stale = False
        else:
            job, self._job = self._job, None
            if job is not None:
                f, M = job.take()  # the factor of the last solve's matrix
                if f is not None and f.n == H.shape[0]:
                    self._swap_in(f, M)
        self._launch(H, assembler)  # this matrix's factor, for the next solve
        # the lagged factor no longer fits H: this matrix's own (the job's); a slow CG even with the
        # last matrix's factor: this one's on the main thread next time (NewtonLinearSolver._cg)
        return self._cg(H, b, rtol, self._take_own)

    def _take_own(self):
        job, self._job = self._job, None
        self._swap_in(*job.take())
