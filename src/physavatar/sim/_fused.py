"""Fused Hessian assembly kernels (numba): an element set's Hessian blocks computed and added
straight into the CSR data of the Newton matrix, one element at a time, instead of first
filling an [M, 3k, 3k] array (4 MB for the demo dress's triangles, 11 MB for its hinges) that
a second pass scatters (assembly.Assembler.assemble, terms.FusedBlocks).

Each block is computed by the same code as the unfused kernel (_kernels.membrane_block, the
Gauss–Newton hinge block of _kernels.bending_hessian) and added in the same order as
_kernels.scatter_add adds the flattened array: the assembled matrix is the same bits
(tests/test_sim_speed.py).
"""

from __future__ import annotations

import numba
import numpy as np

from ._kernels import _angle_gradient_real, membrane_block


@numba.njit(cache=True)
def membrane_hessian_into(data, slot, x, tri, G, area, mu, lam, model, project):
    """data[slot[81 f + 9 p + q]] += membrane_hessian(...)[f, p, q], triangle by triangle."""
    R = np.empty((6, 6))
    Kh = np.empty((6, 6))
    block = np.empty((9, 9))
    for f in range(tri.shape[0]):
        membrane_block(x, tri, G, area, mu, lam, model, project, f, R, Kh, block)
        base = 81 * f
        for p in range(9):
            for q in range(9):
                data[slot[base + 9 * p + q]] += block[p, q]


@numba.njit(cache=True)
def bending_gauss_newton_into(data, slot, x, hinges, weight, scale):
    """data[slot[144 h + 12 i + j]] += c ∇θ_i ∇θ_j (c = 2 κb w_h): bending_hessian's
    BENDING_GAUSS_NEWTON blocks, hinge by hinge."""
    X = np.empty((4, 3))
    g = np.empty(12)
    for h in range(hinges.shape[0]):
        for a in range(4):
            for i in range(3):
                X[a, i] = x[hinges[h, a], i]
        _angle_gradient_real(X, g)
        c = 2.0 * scale * weight[h]
        base = 144 * h
        for i in range(12):
            for j in range(12):
                data[slot[base + 12 * i + j]] += c * g[i] * g[j]
