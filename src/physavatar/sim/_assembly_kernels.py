"""numba kernels of the sparse assembly (scatters into CSR slots, the pattern's keys and slots) and
of the CG solver's vector operations (split from ``_kernels``, which holds the elastic terms'
kernels and re-exports these). Each has a plain-numpy twin in assembly.py; the loops are serial on
purpose (docs/simulation.md "The step"): scatters into shared CSR slots must be.
"""

from __future__ import annotations

import numba
import numpy as np

# -- assembly ------------------------------------------------------------------------------------


@numba.njit(cache=True)
def scatter_add(data, slot, values):
    """data[slot[i]] += values[i] (serial: slots repeat)."""
    for i in range(slot.shape[0]):
        data[slot[i]] += values[i]


@numba.njit(cache=True, inline="always")
def _csr_find(indptr, indices, r, c):
    """Position of entry (r, c) in a CSR pattern with sorted rows (binary search in row r), or -1."""
    lo, hi = indptr[r], indptr[r + 1]
    end = hi
    while lo < hi:
        mid = (lo + hi) // 2
        if indices[mid] < c:
            lo = mid + 1
        else:
            hi = mid
    return lo if lo < end and indices[lo] == c else -1


@numba.njit(cache=True, inline="always")
def _element_dofs(dof_map, index, e, red):
    for a in range(index.shape[1]):
        for i in range(3):
            red[3 * a + i] = dof_map[3 * index[e, a] + i]


@numba.njit(cache=True)
def element_keys(dof_map, index, n):
    """r·n + c of each entry of the element blocks (index [M, k], blocks [3k, 3k]) whose reduced
    row r and column c are both kept (dof_map ≥ 0): Assembler's pattern keys."""
    nk = 3 * index.shape[1]
    red = np.empty(nk, np.int64)
    out = np.empty(index.shape[0] * nk * nk, np.int64)
    m = 0
    for e in range(index.shape[0]):
        _element_dofs(dof_map, index, e, red)
        for p in range(nk):
            if red[p] < 0:
                continue
            for q in range(nk):
                if red[q] >= 0:
                    out[m] = red[p] * n + red[q]
                    m += 1
    return out[:m]


@numba.njit(cache=True)
def element_slots(dof_map, index, indptr, indices, dump):
    """[M·3k·3k] slot in the CSR pattern of each entry of each element block, or ``dump`` where
    its row or column is eliminated (Assembler._element_slots_numpy is the twin)."""
    nk = 3 * index.shape[1]
    red = np.empty(nk, np.int64)
    out = np.empty(index.shape[0] * nk * nk, np.int64)
    m = 0
    for e in range(index.shape[0]):
        _element_dofs(dof_map, index, e, red)
        for p in range(nk):
            r = red[p]
            for q in range(nk):
                c = red[q]
                out[m] = dump if r < 0 or c < 0 else _csr_find(indptr, indices, r, c)
                m += 1
    return out


@numba.njit(cache=True)
def csr_slots(indptr, indices, rows, cols):
    """Position of each entry (rows[k], cols[k]) in a CSR pattern with sorted rows, or -1
    (binary search within the row; Assembler._sparse_slots_numpy is the twin)."""
    out = np.empty(rows.shape[0], np.int64)
    for k in range(rows.shape[0]):
        out[k] = _csr_find(indptr, indices, rows[k], cols[k])
    return out


# -- conjugate gradients -------------------------------------------------------------------------
# The vector operations of assembly.pcg. numpy's 1-D dot / norm call the threaded BLAS, whose
# threads wake and spin on every call, far slower for these short vectors than a plain loop
# (docs/simulation.md "The step").


@numba.njit(cache=True)
def dot(a, b):
    """a · b (serial loop, summed in index order)."""
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


@numba.njit(cache=True)
def cg_step(x, r, p, Ap, alpha):
    """x += α p; r −= α Ap (in place); returns r · r."""
    s = 0.0
    for i in range(x.shape[0]):
        x[i] += alpha * p[i]
        r[i] -= alpha * Ap[i]
        s += r[i] * r[i]
    return s


@numba.njit(cache=True)
def cg_direction(p, z, beta):
    """p ← z + β p (in place)."""
    for i in range(p.shape[0]):
        p[i] = z[i] + beta * p[i]
