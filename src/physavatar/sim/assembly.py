"""Sparse Hessian assembly with a pattern built once, and the sparse Cholesky solve.

The elastic element sets (triangles, hinges) never change, so their CSR pattern and, for each
entry of each element block, the slot it adds into are computed once (a "scatter map");
assembling is then one ``np.bincount``. Contact Hessians (ipctk, pattern changes every
iteration) are added with scipy on top.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

try:  # cholespy: supernodal Cholesky (CHOLMOD-derived); scipy's LU is the fallback.
    import cholespy
except ImportError:  # pragma: no cover - cholespy is a dependency
    cholespy = None

from .energies import Blocks, Diagonal


class Assembler:
    """Scatter per-element blocks into a fixed CSR pattern over selected DOFs.

    Args:
        dof_map: [D] int, for each DOF of the collision mesh (3 × vertex + axis) its row in the
            reduced system, or -1 for DOFs that are eliminated (prescribed).
        element_sets: list of [M, k] vertex-index arrays (triangles, hinges) whose blocks will
            be assembled.
    """

    def __init__(self, dof_map: np.ndarray, element_sets: list[np.ndarray]):
        self.dof_map = np.asarray(dof_map, dtype=np.int64)
        self.n = int(self.dof_map.max()) + 1 if self.dof_map.size else 0
        n = self.n
        keys = [np.arange(n, dtype=np.int64) * (n + 1)]  # the diagonal is always present
        rowcols = []
        for index in element_sets:
            r, c, valid = self._rows_cols(index)
            rowcols.append((r, c, valid))
            keys.append((r * n + c)[valid])
        keys = np.unique(np.concatenate(keys))
        self.indptr = np.searchsorted(keys // n, np.arange(n + 1)).astype(np.int32)
        self.indices = (keys % n).astype(np.int32)
        self.nnz = len(keys)
        self.diag_slot = np.searchsorted(keys, np.arange(n, dtype=np.int64) * (n + 1))
        self.scatter = {}
        for index, (r, c, valid) in zip(element_sets, rowcols):
            slot = np.full(r.shape, self.nnz, dtype=np.int64)  # invalid -> dump slot
            slot[valid] = np.searchsorted(keys, (r * n + c)[valid])
            self.scatter[id(index)] = slot.ravel()

    def _rows_cols(self, index):
        k = index.shape[1]
        dofs = (3 * index[:, :, None] + np.arange(3)).reshape(len(index), 3 * k)
        red = self.dof_map[dofs]
        r = np.broadcast_to(red[:, :, None], (len(index), 3 * k, 3 * k))
        c = np.broadcast_to(red[:, None, :], (len(index), 3 * k, 3 * k))
        return r, c, (r >= 0) & (c >= 0)

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
        """Sum Blocks / Diagonal / scipy-sparse (full-DOF) Hessians into one reduced CSR."""
        slots, values = [], []
        extra = []
        for h in hessians:
            if h is None:
                continue
            if isinstance(h, list):
                for b in h:
                    slots.append(self.scatter[id(b.index)])
                    values.append(b.values.ravel())
            elif isinstance(h, Blocks):
                slots.append(self.scatter[id(h.index)])
                values.append(h.values.ravel())
            elif isinstance(h, Diagonal):
                keep = self.dof_map[: len(h.values)] >= 0
                slots.append(self.diag_slot[self.dof_map[: len(h.values)][keep]])
                values.append(h.values[keep])
            else:
                extra.append(h)
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


class Factorization:
    """Sparse Cholesky of a symmetric positive-definite CSR matrix (cholespy; scipy fallback).

    cholespy redoes the symbolic analysis on every construction (it exposes no separate
    numeric refactorisation); the contact pattern changes each Newton iteration anyway.
    """

    def __init__(self, H: sp.csr_matrix):
        self.n = H.shape[0]
        H = H.tocsr()
        H.sort_indices()
        self._lu = None
        self._chol = None
        if cholespy is not None:
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
        if self._chol is None:
            import scipy.sparse.linalg as sla

            self._lu = sla.splu(H.tocsc())

    def solve(self, b: np.ndarray) -> np.ndarray:
        """b: [n] or [n, k]."""
        b = np.ascontiguousarray(b, dtype=np.float64)
        if self._chol is not None:
            x = np.zeros_like(b)
            self._chol.solve(b, x)
            return x
        return self._lu.solve(b)
