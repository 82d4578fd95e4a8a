"""Sparse Hessian assembly with a pattern built once, and the Newton linear solve.

The elastic element sets (triangles, hinges) never change, so their CSR pattern and, for each
entry of each element block, the slot it adds into are computed once (a "scatter map");
assembling is then a numba scatter. Contact Hessians (ipctk) are scattered into the same
pattern when their entries lie in it, else added with scipy on top. Newton systems are solved
by CG preconditioned with a reused Cholesky factor of a sparsified matrix (NewtonLinearSolver).
A step's system at its solution is kept as a :class:`Linearization` (for sensitivities).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

try:  # cholespy: supernodal Cholesky (CHOLMOD-derived); scipy's LU is the fallback.
    import cholespy
except ImportError:  # pragma: no cover - cholespy is a dependency
    cholespy = None

from . import _kernels, pardiso
from .terms import Blocks, Diagonal, as_hessian


def unique_int(a: np.ndarray) -> np.ndarray:
    """np.unique of an int array, by sorting: numpy 2.4's hash-based np.unique took ~0.34 s a
    call on the ~2M pattern keys of the demo dress (2 of a simulator's ~3.5 s setup); sorting
    takes a fraction of that, same result."""
    a = np.sort(np.asarray(a).ravel())
    return a[np.r_[True, a[1:] != a[:-1]]] if a.size else a


class Assembler:
    """Scatter per-element blocks into a fixed CSR pattern over selected DOFs.

    Args:
        dof_map: [D] int, for each DOF of the collision mesh (3 × vertex + axis) its row in the
            reduced system, or -1 for DOFs that are eliminated (prescribed).
        element_sets: list of [M, k] vertex-index arrays (triangles, hinges) whose blocks will
            be assembled.
    """

    def __init__(self, dof_map: np.ndarray, element_sets: list[np.ndarray], drop_pairs=None):
        self.dof_map = np.asarray(dof_map, dtype=np.int64)
        # vertex of each reduced DOF, and the vertex pairs (i < j) the CG preconditioner drops
        self.dof_vertex = np.zeros(int(self.dof_map.max()) + 1 if self.dof_map.size else 0, np.int64)
        self.dof_vertex[self.dof_map[self.dof_map >= 0]] = np.flatnonzero(self.dof_map >= 0) // 3
        self.drop_keys = None
        if drop_pairs is not None and len(drop_pairs):
            self._nv = len(self.dof_map) // 3
            lo, hi = np.min(drop_pairs, axis=1), np.max(drop_pairs, axis=1)
            self.drop_keys = unique_int(lo.astype(np.int64) * self._nv + hi)
        self.n = int(self.dof_map.max()) + 1 if self.dof_map.size else 0
        n = self.n
        element_keys = [id(index) for index in element_sets]  # the blocks name their set by identity
        keys = [np.arange(n, dtype=np.int64) * (n + 1)]  # the diagonal is always present
        element_sets = [np.ascontiguousarray(index, dtype=np.int64) for index in element_sets]
        for index in element_sets:  # the kernels index dof_map unchecked
            if index.size and (index.min() < 0 or 3 * index.max() + 2 >= len(self.dof_map)):
                raise IndexError("an element's vertex is outside the DOF map")
        for index in element_sets:  # numba, as _element_keys_numpy
            keys.append(_kernels.element_keys(self.dof_map, index, n))
        keys = np.concatenate(keys)
        keys.sort()  # in place (unique_int sorts a copy)
        keys = keys[np.r_[True, keys[1:] != keys[:-1]]]
        self.indptr = np.searchsorted(keys // n, np.arange(n + 1)).astype(np.int32)
        self.indices = (keys % n).astype(np.int32)
        self.nnz = len(keys)
        self.keys = keys  # sorted r·n + c of the pattern's entries
        self.diag_slot = np.searchsorted(keys, np.arange(n, dtype=np.int64) * (n + 1))
        self._sparsified = self._sparsified_pattern() if self.drop_keys is not None else None
        self.scatter = {}
        # invalid -> dump slot (numba, as _element_slots_numpy); int32 when the pattern allows:
        # the scatter reads half the index bytes (2.0 -> 1.1 ms for the demo's 1.4M hinge entries)
        slot_type = np.int32 if self.nnz < 2**31 - 1 else np.int64
        for index, key in zip(element_sets, element_keys):
            slots = _kernels.element_slots(self.dof_map, index, self.indptr, self.indices, self.nnz)
            self.scatter[key] = slots.astype(slot_type)

    def _element_keys_numpy(self, index):
        """Reference twin of ``_kernels.element_keys``."""
        r, c, valid = self._rows_cols(index)
        return (r * self.n + c)[valid]

    def _element_slots_numpy(self, index):
        """Reference twin of ``_kernels.element_slots`` (a search among all pattern keys)."""
        r, c, valid = self._rows_cols(index)
        slot = np.full(r.shape, self.nnz, dtype=np.int64)
        slot[valid] = np.searchsorted(self.keys, (r * self.n + c)[valid])
        return slot.ravel()

    def _rows_cols(self, index):
        k = index.shape[1]
        dofs = (3 * index[:, :, None] + np.arange(3)).reshape(len(index), 3 * k)
        red = self.dof_map[dofs]
        r = np.broadcast_to(red[:, :, None], (len(index), 3 * k, 3 * k))
        c = np.broadcast_to(red[:, None, :], (len(index), 3 * k, 3 * k))
        return r, c, (r >= 0) & (c >= 0)

    def _dropped(self, row, col):
        """Mask of the entries (reduced row, col) that join two ``drop_pairs`` vertices."""
        vr, vc = self.dof_vertex[row], self.dof_vertex[col]
        key = np.minimum(vr, vc) * self._nv + np.maximum(vr, vc)
        pos = np.minimum(np.searchsorted(self.drop_keys, key), len(self.drop_keys) - 1)
        return self.drop_keys[pos] == key

    def _sparsified_pattern(self):
        """The fixed pattern's entries kept by :meth:`preconditioner_matrix` (its CSR pattern and
        slots) and the dropped ones (slots, rows): a matrix in the pattern is then sparsified
        by gathers, without searching the drop pairs each time."""
        n = self.n
        row = np.repeat(np.arange(n, dtype=np.int64), np.diff(self.indptr))
        drop = self._dropped(row, self.indices.astype(np.int64))
        keep = np.flatnonzero(~drop)
        indptr = np.r_[0, np.cumsum(np.bincount(row[keep], minlength=n))].astype(np.int32)
        indices = self.indices[keep]
        kept_diag = np.searchsorted(self.keys[keep], np.arange(n, dtype=np.int64) * (n + 1))
        return dict(keep=keep, indptr=indptr, indices=indices, diag=kept_diag,
                    drop=np.flatnonzero(drop), drop_row=row[drop])

    def preconditioner_matrix(self, H: sp.csr_matrix) -> sp.csr_matrix:
        """H without the entries between ``drop_pairs`` vertices, their |values| moved to the
        diagonal (Gershgorin: the result is ⪰ H, so positive definite when H is)."""
        if self.drop_keys is None:
            return H
        z = self._sparsified
        if (H.nnz == self.nnz and H.has_canonical_format and pardiso.same_or_equal(H.indptr, self.indptr)
                and pardiso.same_or_equal(H.indices, self.indices)):  # H in the fixed pattern: gathers
            comp = np.bincount(z["drop_row"], weights=np.abs(H.data[z["drop"]]), minlength=self.n)
            data = H.data[z["keep"]]
            data[z["diag"]] += comp
            return sp.csr_matrix((data, z["indices"], z["indptr"]), shape=H.shape)
        return self._preconditioner_matrix_coo(H)

    def _preconditioner_matrix_coo(self, H):
        """Twin of :meth:`preconditioner_matrix` for any pattern (contacts outside the fixed one)."""
        H = H.tocsr()
        if not H.has_canonical_format:
            H = H.copy()
            H.sum_duplicates()
        row = np.repeat(np.arange(H.shape[0], dtype=np.int64), np.diff(H.indptr))
        drop = self._dropped(row, H.indices.astype(np.int64))
        comp = np.bincount(row[drop], weights=np.abs(H.data[drop]), minlength=H.shape[0])
        keep = ~drop  # dropped entries must leave the pattern, or the factor keeps their fill
        row, col, data = row[keep], H.indices[keep], H.data[keep]
        diag = row == col
        data[diag] += comp[row[diag]]
        # H's pattern always holds the diagonal (Assembler), so every row's |dropped| lands
        indptr = np.r_[0, np.cumsum(np.bincount(row, minlength=H.shape[0]))].astype(np.int32)
        return sp.csr_matrix((data, col.astype(np.int32), indptr), shape=H.shape)

    def reduce(self, vector: np.ndarray) -> np.ndarray:
        """Full-DOF vector [D] -> reduced [n]."""
        out = np.zeros(self.n)
        keep = self.dof_map >= 0
        out[self.dof_map[keep]] = vector[keep]
        return out

    def expand(self, reduced: np.ndarray) -> np.ndarray:
        """Reduced [n] -> full-DOF vector [D] with zeros on eliminated DOFs."""
        out = np.zeros(len(self.dof_map))
        keep = self.dof_map >= 0
        out[keep] = reduced[self.dof_map[keep]]
        return out

    def assemble(self, hessians) -> sp.csr_matrix:
        """Sum Hessians (terms.Hessian, or scipy-sparse over all DOFs) into one reduced CSR.

        Blocks and diagonals go through their precomputed slots (numba scatter). A sparse
        (contact) Hessian whose entries all lie in the fixed pattern is scattered the same way,
        so the matrix keeps its pattern (and its cached symbolic factorization); otherwise it
        is added with scipy and the pattern grows. Blocks over an element set the assembler
        was not built with (a new term's) take the sparse path. :meth:`assemble_numpy` is the
        twin.
        """
        data = np.zeros(self.nnz + 1)  # the last slot collects entries on eliminated DOFs
        extra = []
        for h in hessians:
            for b in as_hessian(h).parts():
                slot = self.scatter.get(id(b.index)) if isinstance(b, Blocks) else None
                if slot is not None:
                    _kernels.scatter_add(data, slot, np.ascontiguousarray(b.values, dtype=np.float64).ravel())
                elif isinstance(b, Diagonal):
                    keep = self.dof_map[: len(b.values)] >= 0
                    _kernels.scatter_add(data, self.diag_slot[self.dof_map[: len(b.values)][keep]],
                                         np.ascontiguousarray(b.values[keep], dtype=np.float64))
                else:
                    M = b.to_sparse(len(self.dof_map))
                    slot, values = self._sparse_slots(M)
                    if slot is None:
                        extra.append(M)
                    else:
                        _kernels.scatter_add(data, slot, values)
        H = sp.csr_matrix((data[: self.nnz], self.indices, self.indptr), shape=(self.n, self.n))
        for h in extra:
            H = H + self.reduce_matrix(h)
        return H

    def _sparse_slots(self, M):
        """Slots of a full-DOF sparse matrix's kept entries in the pattern, or (None, None).

        Each entry is found by a binary search in its row of the CSR pattern (numba,
        _kernels.csr_slots); :meth:`_sparse_slots_numpy` is the twin (a search in all keys).
        """
        M = M.tocoo()
        r = self.dof_map[M.row]
        c = self.dof_map[M.col]
        keep = (r >= 0) & (c >= 0)
        if self.nnz == 0:
            return (None, None) if np.any(keep) else (np.zeros(0, np.int64), np.zeros(0))
        pos = _kernels.csr_slots(self.indptr, self.indices, r[keep], c[keep])
        if np.any(pos < 0):
            return None, None
        return pos, np.ascontiguousarray(M.data[keep], dtype=np.float64)

    def _sparse_slots_numpy(self, M):
        """Reference twin of :meth:`_sparse_slots`."""
        M = M.tocoo()
        r = self.dof_map[M.row]
        c = self.dof_map[M.col]
        keep = (r >= 0) & (c >= 0)
        key = r[keep] * self.n + c[keep]
        if self.nnz == 0:
            return (None, None) if len(key) else (np.zeros(0, np.int64), np.zeros(0))
        pos = np.searchsorted(self.keys, key)
        if np.any(pos >= self.nnz) or np.any(self.keys[np.minimum(pos, self.nnz - 1)] != key):
            return None, None
        return pos, np.ascontiguousarray(M.data[keep], dtype=np.float64)

    def assemble_numpy(self, hessians) -> sp.csr_matrix:
        """Reference twin of :meth:`assemble` (np.bincount, contact added with scipy)."""
        slots, values = [], []
        extra = []
        for h in hessians:
            for b in as_hessian(h).parts():
                if isinstance(b, Blocks) and id(b.index) in self.scatter:
                    slots.append(self.scatter[id(b.index)])
                    values.append(b.values.ravel())
                elif isinstance(b, Diagonal):
                    keep = self.dof_map[: len(b.values)] >= 0
                    slots.append(self.diag_slot[self.dof_map[: len(b.values)][keep]])
                    values.append(b.values[keep])
                else:
                    extra.append(b.to_sparse(len(self.dof_map)))
        data = np.bincount(
            np.concatenate(slots) if slots else np.zeros(0, np.int64),
            weights=np.concatenate(values) if values else None,
            minlength=self.nnz + 1,
        )[: self.nnz]
        H = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))
        for h in extra:
            H = H + self.reduce_matrix(h)
        return H

    def reduce_matrix(self, M) -> sp.csr_matrix:
        """A full-DOF sparse matrix restricted to the reduced DOFs."""
        M = M.tocoo()
        r = self.dof_map[M.row]
        c = self.dof_map[M.col]
        keep = (r >= 0) & (c >= 0)
        return sp.csr_matrix((M.data[keep], (r[keep], c[keep])), shape=(self.n, self.n))


BACKENDS = ("auto", "cholespy", "pardiso")
PARDISO_MIN_ROWS = 3000  # "auto": PARDISO from this size on (the demo dress: 10k rows)
PRECONDITIONERS = ("auto", "sparsified", "full")


def uses_pardiso(backend: str, n: int) -> bool:
    """Whether a factorisation of an n-row matrix with ``backend`` is PARDISO's ("auto": from
    PARDISO_MIN_ROWS rows on, when MKL is installed)."""
    return backend == "pardiso" or (backend == "auto" and n >= PARDISO_MIN_ROWS and pardiso.available())


class Factorization:
    """Sparse Cholesky of a symmetric positive-definite CSR matrix.

    ``backend``: "cholespy" (supernodal, its own reference BLAS; redoes the symbolic analysis
    on every construction), "pardiso" (Intel MKL PARDISO, ``sim.pardiso``; the optional
    ``mkl`` extra) or "auto" (PARDISO for matrices of at least PARDISO_MIN_ROWS rows when MKL
    is installed, else cholespy: below that neither is faster, and small systems keep their
    results bit-identical to cholespy's; docs/simulation.md "Session 21"). scipy's LU is the
    fallback of either when the matrix is not numerically positive definite. ``reuse`` /
    ``move``: an earlier factor of the same pattern whose PARDISO analysis is reused
    (``PardisoCholesky``); ignored by cholespy, and so is ``threads`` (PARDISO's).
    """

    def __init__(self, H: sp.csr_matrix, backend: str = "auto", reuse: "Factorization | None" = None,
                 move: bool = False, threads: int = 1):
        if backend not in BACKENDS:
            raise ValueError(f"linear solver backend {backend!r}: expected one of {BACKENDS}")
        self.n = H.shape[0]
        H = H.tocsr()
        H.sort_indices()
        self._lu = None
        self._chol = None
        self._pardiso = None
        indefinite = False
        if uses_pardiso(backend, self.n):
            try:
                old = reuse._pardiso if reuse is not None else None
                self._pardiso = pardiso.PardisoCholesky(H, old, move and old is not None, threads)
            except pardiso.PardisoError:
                indefinite = True  # not positive definite numerically: LU below
            except ValueError:
                if backend == "pardiso":
                    raise
        if self._pardiso is None and not indefinite and cholespy is not None:
            try:
                self._chol = cholespy.CholeskySolverD(
                    self.n,
                    H.indptr.astype(np.int32),
                    H.indices.astype(np.int32),
                    np.ascontiguousarray(H.data, dtype=np.float64),
                    cholespy.MatrixType.CSR,
                )
            except (ValueError, RuntimeError):
                self._chol = None  # not positive definite numerically: fall back to LU
        if self._chol is None and self._pardiso is None:
            import scipy.sparse.linalg as sla

            self._lu = sla.splu(H.tocsc())

    @property
    def backend(self) -> str:
        return "pardiso" if self._pardiso is not None else "cholespy" if self._chol is not None else "lu"

    def solve(self, b: np.ndarray) -> np.ndarray:
        """b: [n] or [n, k]."""
        b = np.ascontiguousarray(b, dtype=np.float64)
        if self._pardiso is not None:
            return self._pardiso.solve(b)
        if self._chol is not None:
            x = np.zeros_like(b)
            self._chol.solve(b, x)
            return x
        return self._lu.solve(b)


class NewtonLinearSolver:
    """Solves the Newton systems H d = b of consecutive iterations by preconditioned CG.

    The preconditioner is the Cholesky factor of a *sparsified* H: the entries coupling the
    two tips of a hinge (vertices that share no edge; only bending puts them in the pattern)
    are dropped and their magnitudes added to both diagonals (H₁ = H − Drop + D with
    D ⪰ Drop, so H₁ ⪰ H ≻ 0 stays positive definite). H₁ has the 1-ring pattern: its factor
    is much cheaper than H's, and CG reaches ‖H d − b‖ ≤ ``rtol`` ‖b‖ (1e-6: the Newton
    iterates match a direct solve) in a few tens of iterations (docs/simulation.md "The
    step"). The factor is also reused across the Newton iterations of a step while CG
    converges quickly (ClothSim marks it stale at each new step: :meth:`mark_stale`); after a
    solve that needed more than ``refresh_cg`` iterations (default by backend, REFRESH_CG:
    cholespy 20, a factorisation costs ~30–60 CG iterations of CPU time, docs/simulation.md
    "Session 15"; PARDISO 10, its numeric factorisation ~8× cheaper, "Session 21") it is
    recomputed from the next H,
    and when CG fails within ``max_cg`` (the state or contacts changed a lot) it is recomputed
    from the current H at once.

    ``preconditioner``: "sparsified" (H₁ above), "full" (a factor of H itself: a fresh one
    solves exactly, then it ages like H₁'s) or "auto": "full" for systems of at least
    ``FULL_MIN_ROWS`` rows when the factorisation is PARDISO's (there H₁ needs ~50 CG
    iterations even when fresh, and PARDISO factorises H in the time of ~25 of them; the
    demo dress's 10k-row systems need 5; docs/simulation.md "Session 21"), else "sparsified".

    ``max_cg=0`` factorises H itself every call (plain Newton; the reference behaviour).
    """

    FULL_MIN_ROWS = 30000

    REFRESH_CG = {"cholespy": 20, "pardiso": 10, "lu": 20}

    def __init__(self, rtol: float = 1e-6, max_cg: int = 100, refresh_cg: int | None = None, backend: str = "auto",
                 preconditioner: str = "auto", threads: int = 1):
        if preconditioner not in PRECONDITIONERS:
            raise ValueError(f"preconditioner {preconditioner!r}: expected one of {PRECONDITIONERS}")
        self.rtol = float(rtol)
        self.max_cg = int(max_cg)
        self.refresh_cg = refresh_cg  # None: by the factor's backend (REFRESH_CG)
        self.backend = backend
        self.preconditioner = preconditioner
        self.threads = int(threads)
        self.factorizations = 0
        self.cg_iterations = 0
        self.reset()

    def reset(self):
        self.factor: Factorization | None = None
        self.factor_matrix = None  # the matrix self.factor factorises
        self._stale = True
        self._given = True

    def mark_stale(self, keep: bool = True):
        """Take a fresh factor at the next solve (a new step: the old factor preconditioned the
        previous step's matrices, which rarely fit well enough to be worth trying).

        ``keep``: the old factor may be held by the last step's Linearization (its
        sensitivities), so the next one is a new object (a PARDISO factor with a new handle:
        its symbolic analysis again, with the old ordering). With ``keep=False`` the next
        factor takes over the old one's PARDISO handle, as the refactorisations within a step
        do (Factorization ``move``: the numeric phase only; the same factor bits), and the old
        one can no longer solve."""
        self._stale = True
        self._given = keep

    def _preconditioner_matrix(self, H, assembler):
        full = self.preconditioner == "full" or (
            self.preconditioner == "auto" and H.shape[0] >= self.FULL_MIN_ROWS and uses_pardiso(self.backend, H.shape[0]))
        return H if full else assembler.preconditioner_matrix(H)

    def _refactor(self, M):
        self.factor = Factorization(M, self.backend, self.factor, move=not self._given, threads=self.threads)
        self._given = False
        self.factor_matrix = M
        self.factorizations += 1

    def solve(self, H: sp.csr_matrix, b: np.ndarray, assembler: "Assembler | None" = None,
              rtol: float | None = None) -> np.ndarray:
        rtol = self.rtol if rtol is None else max(float(rtol), self.rtol)
        if self.max_cg <= 0 or assembler is None:
            self._refactor(H)
            self._stale = True
            return self.factor.solve(b)
        if self.factor is None or self._stale or self.factor.n != H.shape[0]:
            self._refactor(self._preconditioner_matrix(H, assembler))
            self._stale = False
        # the old factor no longer fits H: a fresh one
        return self._cg(H, b, rtol, lambda: self._refactor(self._preconditioner_matrix(H, assembler)))

    def _cg(self, H: sp.csr_matrix, b: np.ndarray, rtol: float, refit) -> np.ndarray:
        """CG on H x = b with the current factor as preconditioner; where it does not converge,
        ``refit()`` installs a factor that fits H and CG runs again, and where that fails too a
        direct solve answers. The next solve refactorises first when this one's CG took more than
        the backend's ``REFRESH_CG`` iterations."""
        x, its, ok = pcg(H, b, self.factor.solve, rtol, self.max_cg)
        self.cg_iterations += its
        if not ok:
            refit()
            x, its, ok = pcg(H, b, self.factor.solve, rtol, self.max_cg)
            self.cg_iterations += its
            if not ok:  # not expected (H₁ ⪰ H); a direct solve is always right
                self._refactor(H)
                self._stale = True
                return self.factor.solve(b)
        refresh = self.REFRESH_CG[self.factor.backend] if self.refresh_cg is None else self.refresh_cg
        self._stale = its > refresh
        return x

    def refine(self, H: sp.csr_matrix, b: np.ndarray, x: np.ndarray, assembler=None) -> np.ndarray:
        """Continue CG on H x = b from x to ‖H x − b‖ ≤ 1e-10 ‖b‖ (with a fresh preconditioner
        if the old one stalls, a direct solve if that stalls too).

        The Newton stopping test reads ‖Δx‖∞, and with the barrier's conditioning a 1e-6
        relative residual can still leave Δx visibly wrong; the step that is about to end the
        solve is therefore made exact before it is trusted (only that one, so cheap).
        """
        if self.factor is None or self.factor_matrix is H:
            return x  # came from a direct factorisation of H: already exact
        x, its, ok = pcg(H, b, self.factor.solve, 1e-10, self.max_cg, x0=x)
        self.cg_iterations += its
        if ok:
            return x
        if assembler is not None:
            self._refactor(self._preconditioner_matrix(H, assembler))
            x, its, ok = pcg(H, b, self.factor.solve, 1e-10, self.max_cg, x0=x)
            self.cg_iterations += its
            if ok:
                return x
        self._refactor(H)
        self._stale = True
        return self.factor.solve(b)


class Linearization:
    """The step's system at (or next to) its solution, for adjoint/forward sensitivities.

    dof_map: [3(N+Nb)] reduced row of each DOF (-1 = prescribed). matrix: the last projected
    Newton matrix (CSR over the reduced DOFs). factorization: its Cholesky factor, computed on
    first access (the Newton solve itself may have used an older factor as a CG
    preconditioner, assembly.NewtonLinearSolver). hessian: exact unprojected ∇²E at the
    solution ``positions`` (CSR over the free DOFs), or None unless
    SimSettings.keep_linearization. preconditioner: the factor the free system's Newton solver
    held at the end of the step (of a sparsified projected matrix), or None.
    """

    def __init__(self, dof_map: np.ndarray, matrix, hessian=None, factorization=None, positions=None,
                 preconditioner=None):
        self.dof_map = dof_map
        self.matrix = matrix
        self.hessian = hessian
        self.positions = positions
        self.preconditioner = preconditioner
        self._factorization = factorization

    @property
    def factorization(self) -> Factorization | None:
        if self._factorization is None and self.matrix is not None:
            self._factorization = Factorization(self.matrix)
        return self._factorization

    def preconditioners(self, n: int):
        """Solves with Cholesky factors of the step's PSD-projected Newton matrix over the free
        DOFs, cheapest first: the (sparsified) factor the Newton solver held, then a factor of
        the last projected matrix itself (computed only when asked). Each is a callable that
        returns a solve ([n] -> [n]) or None when it does not have ``n`` rows (a step that
        ended in penalty mode)."""

        def held():
            f = self.preconditioner
            return f.solve if f is not None and getattr(f, "n", -1) == n else None

        def fresh():
            if self.matrix is None or self.matrix.shape[0] != n:
                return None
            try:
                return self.factorization.solve
            except (RuntimeError, ValueError):
                return None

        return (held, fresh)


def pcg(A, b, precondition, rtol, max_iterations, x0=None):
    """Preconditioned conjugate gradients from x0 (default M⁻¹ b: one preconditioner step).

    Returns (x, iterations, converged) with converged meaning ‖A x − b‖₂ ≤ rtol ‖b‖₂. The
    vector operations are numba loops (_kernels.dot / cg_step / cg_direction), not BLAS.
    """
    b = np.ascontiguousarray(b, dtype=np.float64)
    bnorm = np.sqrt(_kernels.dot(b, b))
    if bnorm == 0.0:
        return np.zeros_like(b), 0, True
    x = precondition(b) if x0 is None else np.array(x0, dtype=np.float64)
    x = np.ascontiguousarray(x, dtype=np.float64)
    r = b - A @ x
    tol2 = (rtol * bnorm) ** 2
    if _kernels.dot(r, r) <= tol2:
        return x, 0, True
    z = np.ascontiguousarray(precondition(r), dtype=np.float64)
    p = z.copy()
    rz = _kernels.dot(r, z)
    for it in range(1, max_iterations + 1):
        Ap = np.ascontiguousarray(A @ p, dtype=np.float64)
        pAp = _kernels.dot(p, Ap)
        if not pAp > 0.0:  # A not positive definite along p: let the caller factorise A
            return x, it, False
        a = rz / pAp
        if _kernels.cg_step(x, r, p, Ap, a) <= tol2:
            return x, it, True
        z = np.ascontiguousarray(precondition(r), dtype=np.float64)
        rz_new = _kernels.dot(r, z)
        _kernels.cg_direction(p, z, rz_new / rz)
        rz = rz_new
    return x, max_iterations, False
