"""numba kernels for the per-element work of the elastic terms; those of the sparse assembly and
of CG are in _assembly_kernels (re-exported here).

Each kernel has a plain-numpy twin in energies.py / assembly.py (the reference) and
tests/test_sim_kernels.py holds the fast one to it. The loops are serial on purpose: a
gradient is well under a millisecond of work, less than numba's parallel=True costs in thread
start and barriers on a loaded machine (docs/simulation.md "The step"). Scatters into shared
vertex rows / CSR slots must be serial anyway.

Conventions are those of energies.py: x [N, 3], gradients [N, 3] (flattened by the caller),
membrane blocks [F, 9, 9] and hinge blocks [H, 12, 12] ordered (vertex, axis).
"""

from __future__ import annotations

import math

import numba
import numpy as np

# -- membrane ------------------------------------------------------------------------------------

MODEL_STVK = 0
MODEL_NEOHOOKEAN = 1


@numba.njit(cache=True, inline="always")
def _deformation_gradient(x, tri, G, f, F):
    for i in range(3):
        for j in range(2):
            s = 0.0
            for a in range(3):
                s += x[tri[f, a], i] * G[f, a, j]
            F[i, j] = s


@numba.njit(cache=True, inline="always")
def _second_piola(F, mu, lam, model, S, C, Cinv):
    """S [2, 2] from F [3, 2]; fills C and (Neo-Hookean) Cinv; returns log J (0 for StVK)."""
    for i in range(2):
        for j in range(2):
            C[i, j] = F[0, i] * F[0, j] + F[1, i] * F[1, j] + F[2, i] * F[2, j]
    if model == MODEL_STVK:
        trE = 0.5 * (C[0, 0] - 1.0 + C[1, 1] - 1.0)
        for i in range(2):
            for j in range(2):
                S[i, j] = mu * (C[i, j] - (1.0 if i == j else 0.0))
            S[i, i] += lam * trE
        return 0.0
    det = C[0, 0] * C[1, 1] - C[0, 1] * C[1, 0]
    logJ = 0.5 * math.log(det)
    Cinv[0, 0] = C[1, 1] / det
    Cinv[0, 1] = -C[0, 1] / det
    Cinv[1, 0] = -C[1, 0] / det
    Cinv[1, 1] = C[0, 0] / det
    for i in range(2):
        for j in range(2):
            S[i, j] = (lam * logJ - mu) * Cinv[i, j] + (mu if i == j else 0.0)
    return logJ


@numba.njit(cache=True)
def membrane_energy(x, tri, G, area, mu, lam, model):
    """Σ_t A_t W(F_t) (inf when a Neo-Hookean triangle is collapsed or inverted, as the twin)."""
    total = 0.0
    F = np.empty((3, 2))
    for f in range(tri.shape[0]):
        _deformation_gradient(x, tri, G, f, F)
        c00 = F[0, 0] * F[0, 0] + F[1, 0] * F[1, 0] + F[2, 0] * F[2, 0]
        c01 = F[0, 0] * F[0, 1] + F[1, 0] * F[1, 1] + F[2, 0] * F[2, 1]
        c11 = F[0, 1] * F[0, 1] + F[1, 1] * F[1, 1] + F[2, 1] * F[2, 1]
        if model == MODEL_STVK:
            e00, e01, e11 = 0.5 * (c00 - 1.0), 0.5 * c01, 0.5 * (c11 - 1.0)
            tr = e00 + e11
            W = mu * (e00 * e00 + 2.0 * e01 * e01 + e11 * e11) + 0.5 * lam * tr * tr
        else:
            det = c00 * c11 - c01 * c01
            if not det > 0.0:
                return np.inf
            logJ = 0.5 * math.log(det)
            W = 0.5 * mu * (c00 + c11 - 2.0) - mu * logJ + 0.5 * lam * logJ * logJ
        total += area[f] * W
    return total


@numba.njit(cache=True)
def membrane_gradient(x, tri, G, area, mu, lam, model, n_vertices):
    """∇Ψ_membrane [n_vertices, 3] (Neo-Hookean on a collapsed triangle: nan, as the twin)."""
    nf = tri.shape[0]
    per = np.empty((nf, 3, 3))
    F = np.empty((3, 2))  # scratch, overwritten for each triangle (allocated once)
    S = np.empty((2, 2))
    C = np.empty((2, 2))
    Cinv = np.empty((2, 2))
    for f in range(nf):
        _deformation_gradient(x, tri, G, f, F)
        _second_piola(F, mu, lam, model, S, C, Cinv)
        for i in range(3):
            P0 = F[i, 0] * S[0, 0] + F[i, 1] * S[1, 0]
            P1 = F[i, 0] * S[0, 1] + F[i, 1] * S[1, 1]
            for a in range(3):
                per[f, a, i] = area[f] * (P0 * G[f, a, 0] + P1 * G[f, a, 1])
    out = np.zeros((n_vertices, 3))
    for f in range(nf):  # serial: triangles share vertices
        for a in range(3):
            for i in range(3):
                out[tri[f, a], i] += per[f, a, i]
    return out


@numba.njit(cache=True, inline="always")
def _is_positive_definite(K, n, Q):
    """Cholesky attempt on symmetric K [n, n] (n³/6 flops; Q is scratch)."""
    for i in range(n):
        for j in range(n):
            Q[i, j] = K[i, j]
    for j in range(n):
        d = Q[j, j]
        for k in range(j):
            d -= Q[j, k] * Q[j, k]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        Q[j, j] = d
        for i in range(j + 1, n):
            t = Q[i, j]
            for k in range(j):
                t -= Q[i, k] * Q[j, k]
            Q[i, j] = t / d
    return True


@numba.njit(cache=True, inline="always")
def _project_psd(K, n, Q, absolute=False):
    """Clamp (or, ``absolute``, flip) the negative eigenvalues of symmetric K [n, n] in place.

    A Cholesky attempt (n³/6 flops) first: blocks that are positive definite (triangles in
    tension, most of them) are left as they are without the far costlier eigendecomposition.
    """
    if not _is_positive_definite(K, n, Q):
        _clamp_eigenvalues(K, n, Q, absolute)


@numba.njit(cache=True, inline="always")
def _clamp_eigenvalues(K, n, Q, absolute=False):
    """The eigendecomposition half of :func:`_project_psd` (K known not positive definite)."""
    w, V = np.linalg.eigh(K)
    if w[0] >= 0.0:
        return
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                if w[k] > 0.0:
                    s += V[i, k] * w[k] * V[j, k]
                elif absolute:
                    s -= V[i, k] * w[k] * V[j, k]
            Q[i, j] = s
    for i in range(n):
        for j in range(n):
            K[i, j] = Q[i, j]


@numba.njit(cache=True, inline="always")
def _clamp_sym2(a, b, c, absolute):
    """Eigenvalue-clamped (``absolute``: flipped) symmetric [[a, b], [b, c]] -> (a, b, c)."""
    if not absolute and a >= 0.0 and c >= 0.0 and a * c - b * b >= 0.0:
        return a, b, c
    h = 0.5 * (a + c)
    d = math.sqrt(0.25 * (a - c) * (a - c) + b * b)
    l1, l2 = h + d, h - d
    if absolute:
        l1, l2 = abs(l1), abs(l2)
    else:
        l1, l2 = max(l1, 0.0), max(l2, 0.0)
    t = 0.5 * math.atan2(2.0 * b, a - c)  # (cos t, sin t): eigenvector of h + d
    cs, sn = math.cos(t), math.sin(t)
    return l1 * cs * cs + l2 * sn * sn, (l1 - l2) * cs * sn, l1 * sn * sn + l2 * cs * cs


# the 2×2 blocks of ∂²W/∂F² in the singular frame, as (vec F̂ index 2a + b) pairs
_BLOCKS = ((0, 3), (1, 2), (4, 5))


@numba.njit(cache=True, inline="always")
def _project_psd_isotropic(K, F, R, Kh, absolute, U, V, T):
    """Eigenvalue clamp of an isotropic energy's ∂²W/∂F² [6, 6] (F [3, 2]) in closed form.

    With F = Ū Σ Vᵀ (Ū = [u₁ u₂ n]) and δF = Ū δF̂ Vᵀ, the Hessian of any isotropic W is
    block diagonal in δF̂ (Smith et al. 2019, "Analytic eigensystems for isotropic distortion
    energies", here for 3×2 F): the stretch pair (F̂₁₁, F̂₂₂), the in-plane twist/flip pair
    (F̂₁₂, F̂₂₁) and the out-of-plane pair (F̂₃₁, F̂₃₂). The blocks are rotated out of K
    numerically (no energy-specific formula), clamped as 2×2s and rotated back: the same
    matrix as the clamped eigendecomposition, ~8× cheaper. Returns False (K untouched) for
    near-degenerate triangles or when the blocks do not separate; the caller then uses eigh.
    U [3, 3], V [2, 2], T [6, 6]: scratch (every entry written before it is read).
    """
    c00 = F[0, 0] * F[0, 0] + F[1, 0] * F[1, 0] + F[2, 0] * F[2, 0]
    c01 = F[0, 0] * F[0, 1] + F[1, 0] * F[1, 1] + F[2, 0] * F[2, 1]
    c11 = F[0, 1] * F[0, 1] + F[1, 1] * F[1, 1] + F[2, 1] * F[2, 1]
    h = 0.5 * (c00 + c11)
    d = math.sqrt(0.25 * (c00 - c11) * (c00 - c11) + c01 * c01)
    e1, e2 = h + d, h - d
    if not e2 > 1e-6 * e1:
        return False
    t = 0.5 * math.atan2(2.0 * c01, c00 - c11)
    v00, v10 = math.cos(t), math.sin(t)  # V = [[v00, v01], [v10, v11]], columns v₁, v₂
    v01, v11 = -v10, v00
    s1, s2 = math.sqrt(e1), math.sqrt(e2)
    for i in range(3):
        U[i, 0] = (F[i, 0] * v00 + F[i, 1] * v10) / s1
        U[i, 1] = (F[i, 0] * v01 + F[i, 1] * v11) / s2
    U[0, 2] = U[1, 0] * U[2, 1] - U[2, 0] * U[1, 1]
    U[1, 2] = U[2, 0] * U[0, 1] - U[0, 0] * U[2, 1]
    U[2, 2] = U[0, 0] * U[1, 1] - U[1, 0] * U[0, 1]
    V[0, 0], V[0, 1], V[1, 0], V[1, 1] = v00, v01, v10, v11
    for i in range(3):  # R[(i, j), (a, b)] = Ū[i, a] V[j, b]
        for j in range(2):
            for a in range(3):
                for b in range(2):
                    R[2 * i + j, 2 * a + b] = U[i, a] * V[j, b]
    # Kh = Rᵀ K R (Q-free: T = K R first, into Kh's rows via a small buffer)
    for p in range(6):
        for q in range(6):
            acc = 0.0
            for k in range(6):
                acc += K[p, k] * R[k, q]
            T[p, q] = acc
    scale = 0.0
    for p in range(6):
        for q in range(6):
            acc = 0.0
            for k in range(6):
                acc += R[k, p] * T[k, q]
            Kh[p, q] = acc
            scale = max(scale, abs(acc))
    block = np.array([0, 1, 1, 0, 2, 2])
    for p in range(6):
        for q in range(6):
            if block[p] != block[q]:
                if abs(Kh[p, q]) > 1e-9 * scale:
                    return False
                Kh[p, q] = 0.0
    for bi in range(3):
        p, q = _BLOCKS[bi]
        a, b, c = _clamp_sym2(Kh[p, p], 0.5 * (Kh[p, q] + Kh[q, p]), Kh[q, q], absolute)
        Kh[p, p], Kh[p, q], Kh[q, p], Kh[q, q] = a, b, b, c
    for p in range(6):  # K = R Kh Rᵀ
        for q in range(6):
            acc = 0.0
            for k in range(6):
                acc += R[p, k] * Kh[k, q]
            T[p, q] = acc
    for p in range(6):
        for q in range(6):
            acc = 0.0
            for k in range(6):
                acc += T[p, k] * R[q, k]
            K[p, q] = acc
    return True


@numba.njit(cache=True)
def membrane_hessian(x, tri, G, area, mu, lam, model, project):
    """[F, 9, 9] vertex blocks A Gᵀ K G with K = ∂²W/∂F² (6×6, PSD-projected if ``project``)."""
    nf = tri.shape[0]
    out = np.empty((nf, 9, 9))
    R = np.empty((6, 6))
    Kh = np.empty((6, 6))
    # scratch, every entry written for each triangle before it is read: allocated once (a
    # per-triangle allocation was about half the kernel's time; the same arithmetic)
    F = np.empty((3, 2))
    S = np.empty((2, 2))
    C = np.empty((2, 2))
    Cinv = np.empty((2, 2))
    dC = np.empty((2, 2))
    dS = np.empty((2, 2))
    K = np.empty((6, 6))
    Q = np.empty((6, 6))
    U = np.empty((3, 3))
    V = np.empty((2, 2))
    T = np.empty((6, 6))
    for f in range(nf):
        _deformation_gradient(x, tri, G, f, F)
        logJ = _second_piola(F, mu, lam, model, S, C, Cinv)
        for b in range(6):  # column b: δF = e_k e_lᵀ, b = 2k + l
            k, l = b // 2, b % 2
            for i in range(2):  # δC = FᵀδF + δFᵀF
                for j in range(2):
                    dC[i, j] = (F[k, i] if j == l else 0.0) + (F[k, j] if i == l else 0.0)
            if model == MODEL_STVK:
                tr = dC[0, 0] + dC[1, 1]
                for i in range(2):
                    for j in range(2):
                        dS[i, j] = mu * dC[i, j] + (0.5 * lam * tr if i == j else 0.0)
            else:
                tr = 0.0
                for i in range(2):
                    for j in range(2):
                        tr += Cinv[i, j] * dC[j, i]
                c = mu - lam * logJ
                for i in range(2):
                    for j in range(2):
                        s = 0.0
                        for p in range(2):
                            for q in range(2):
                                s += Cinv[i, p] * dC[p, q] * Cinv[q, j]
                        dS[i, j] = c * s + 0.5 * lam * tr * Cinv[i, j]
            for i in range(3):  # δP = δF S + F δS
                for j in range(2):
                    v = S[l, j] if i == k else 0.0
                    v += F[i, 0] * dS[0, j] + F[i, 1] * dS[1, j]
                    K[2 * i + j, b] = v
        for i in range(6):
            for j in range(i + 1, 6):
                s = 0.5 * (K[i, j] + K[j, i])
                K[i, j] = s
                K[j, i] = s
        if project == 3:  # reference path of the tests: the eigendecomposition clamp
            _project_psd(K, 6, Q)
        elif project and not _is_positive_definite(K, 6, Q):
            if not _project_psd_isotropic(K, F, R, Kh, project == 2, U, V, T):
                _clamp_eigenvalues(K, 6, Q, project == 2)
        # H[(a,i),(c,k)] = A Σ_{j,l} G[a,j] K[(i,j),(k,l)] G[c,l]
        for a in range(3):
            for i in range(3):
                for c in range(3):
                    for kk in range(3):
                        s = 0.0
                        for j in range(2):
                            for l in range(2):
                                s += G[f, a, j] * K[2 * i + j, 2 * kk + l] * G[f, c, l]
                        out[f, 3 * a + i, 3 * c + kk] = area[f] * s
    return out


# -- bending -------------------------------------------------------------------------------------

BENDING_EXACT = 0
BENDING_EIGEN = 1
BENDING_GAUSS_NEWTON = 2


@numba.njit(cache=True, inline="always")
def _angle(X):
    """Signed dihedral angle of one hinge X [4, 3] (energies.dihedral_angle)."""
    e0, e1, e2 = X[1, 0] - X[0, 0], X[1, 1] - X[0, 1], X[1, 2] - X[0, 2]
    a0, a1, a2 = X[2, 0] - X[0, 0], X[2, 1] - X[0, 1], X[2, 2] - X[0, 2]
    b0, b1, b2 = X[3, 0] - X[0, 0], X[3, 1] - X[0, 1], X[3, 2] - X[0, 2]
    nA0, nA1, nA2 = e1 * a2 - e2 * a1, e2 * a0 - e0 * a2, e0 * a1 - e1 * a0  # e × a
    nB0, nB1, nB2 = b1 * e2 - b2 * e1, b2 * e0 - b0 * e2, b0 * e1 - b1 * e0  # b × e
    c0, c1, c2 = nA1 * nB2 - nA2 * nB1, nA2 * nB0 - nA0 * nB2, nA0 * nB1 - nA1 * nB0
    le = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    return math.atan2((c0 * e0 + c1 * e1 + c2 * e2) / le, nA0 * nB0 + nA1 * nB1 + nA2 * nB2)


@numba.njit(cache=True, inline="always")
def _angle_gradient(X, g):
    """∂θ/∂X into g [12] (energies.dihedral_angle_gradient); generic over float / complex X."""
    e = X[1] - X[0]
    u = X[2] - X[0]
    w = X[2] - X[1]
    p = X[3] - X[1]
    q = X[3] - X[0]
    n1 = np.array([u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]])
    n2 = np.array([p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]])
    le = np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    n1 = n1 / (n1[0] * n1[0] + n1[1] * n1[1] + n1[2] * n1[2])
    n2 = n2 / (n2[0] * n2[0] + n2[1] * n2[1] + n2[2] * n2[2])
    s20 = (w[0] * e[0] + w[1] * e[1] + w[2] * e[2]) / le  # (x2 − x1)·e / |e|
    s30 = (p[0] * e[0] + p[1] * e[1] + p[2] * e[2]) / le  # (x3 − x1)·e / |e|
    s21 = (u[0] * e[0] + u[1] * e[1] + u[2] * e[2]) / le  # (x2 − x0)·e / |e|
    s31 = (q[0] * e[0] + q[1] * e[1] + q[2] * e[2]) / le  # (x3 − x0)·e / |e|
    for i in range(3):
        g[i] = -s20 * n1[i] - s30 * n2[i]
        g[3 + i] = s21 * n1[i] + s31 * n2[i]
        g[6 + i] = -le * n1[i]
        g[9 + i] = -le * n2[i]


@numba.njit(cache=True, inline="always")
def _angle_gradient_real(X, g):
    """_angle_gradient for real X with scalar temporaries (no per-hinge array allocations)."""
    e0, e1, e2 = X[1, 0] - X[0, 0], X[1, 1] - X[0, 1], X[1, 2] - X[0, 2]
    u0, u1, u2 = X[2, 0] - X[0, 0], X[2, 1] - X[0, 1], X[2, 2] - X[0, 2]
    w0, w1, w2 = X[2, 0] - X[1, 0], X[2, 1] - X[1, 1], X[2, 2] - X[1, 2]
    p0, p1, p2 = X[3, 0] - X[1, 0], X[3, 1] - X[1, 1], X[3, 2] - X[1, 2]
    q0, q1, q2 = X[3, 0] - X[0, 0], X[3, 1] - X[0, 1], X[3, 2] - X[0, 2]
    a0, a1, a2 = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0  # n1
    b0, b1, b2 = p1 * q2 - p2 * q1, p2 * q0 - p0 * q2, p0 * q1 - p1 * q0  # n2
    le = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    na = a0 * a0 + a1 * a1 + a2 * a2
    nb = b0 * b0 + b1 * b1 + b2 * b2
    a0, a1, a2 = a0 / na, a1 / na, a2 / na
    b0, b1, b2 = b0 / nb, b1 / nb, b2 / nb
    s20 = (w0 * e0 + w1 * e1 + w2 * e2) / le
    s30 = (p0 * e0 + p1 * e1 + p2 * e2) / le
    s21 = (u0 * e0 + u1 * e1 + u2 * e2) / le
    s31 = (q0 * e0 + q1 * e1 + q2 * e2) / le
    g[0], g[1], g[2] = -s20 * a0 - s30 * b0, -s20 * a1 - s30 * b1, -s20 * a2 - s30 * b2
    g[3], g[4], g[5] = s21 * a0 + s31 * b0, s21 * a1 + s31 * b1, s21 * a2 + s31 * b2
    g[6], g[7], g[8] = -le * a0, -le * a1, -le * a2
    g[9], g[10], g[11] = -le * b0, -le * b1, -le * b2


@numba.njit(cache=True, inline="always")
def _degenerate(X):
    """A hinge with a triangle of no area to rounding (sine below 1e-12; sim.untangle can flatten
    one onto a body edge): θ is 0/0, the bending kernels leave it out (docs/simulation.md "Session 33")."""
    e0, e1, e2 = X[1, 0] - X[0, 0], X[1, 1] - X[0, 1], X[1, 2] - X[0, 2]
    a0, a1, a2 = X[2, 0] - X[0, 0], X[2, 1] - X[0, 1], X[2, 2] - X[0, 2]
    b0, b1, b2 = X[3, 0] - X[0, 0], X[3, 1] - X[0, 1], X[3, 2] - X[0, 2]
    na = (e1 * a2 - e2 * a1) ** 2 + (e2 * a0 - e0 * a2) ** 2 + (e0 * a1 - e1 * a0) ** 2
    nb = (b1 * e2 - b2 * e1) ** 2 + (b2 * e0 - b0 * e2) ** 2 + (b0 * e1 - b1 * e0) ** 2
    tiny = 1e-24 * (e0 * e0 + e1 * e1 + e2 * e2)  # sine² of the triangle's angle at X[0] below 1e-24
    return na <= tiny * (a0 * a0 + a1 * a1 + a2 * a2) or nb <= tiny * (b0 * b0 + b1 * b1 + b2 * b2)


@numba.njit(cache=True)
def bending_energy(x, hinges, weight, rest_angle, scale):
    """Σ_e κb w_e (θ_e − θ̄_e)² (energies.Bending.energy)."""
    total = 0.0
    X = np.empty((4, 3))
    for h in range(hinges.shape[0]):
        for a in range(4):
            for i in range(3):
                X[a, i] = x[hinges[h, a], i]
        if _degenerate(X):
            continue
        d = _angle(X) - rest_angle[h]
        total += weight[h] * d * d
    return scale * total


@numba.njit(cache=True)
def bending_gradient(x, hinges, weight, rest_angle, scale, n_vertices):
    nh = hinges.shape[0]
    per = np.empty((nh, 12))
    X = np.empty((4, 3))
    g = np.empty(12)
    for h in range(nh):
        for a in range(4):
            for i in range(3):
                X[a, i] = x[hinges[h, a], i]
        if _degenerate(X):  # no force from an undefined angle
            per[h, :] = 0.0
            continue
        _angle_gradient_real(X, g)
        c = 2.0 * scale * weight[h] * (_angle(X) - rest_angle[h])
        for k in range(12):
            per[h, k] = c * g[k]
    out = np.zeros((n_vertices, 3))
    for h in range(nh):  # serial: hinges share vertices
        for a in range(4):
            for i in range(3):
                out[hinges[h, a], i] += per[h, 3 * a + i]
    return out


_COMPLEX_STEP = 1e-30


@numba.njit(cache=True)
def bending_hessian(x, hinges, weight, rest_angle, scale, mode):
    """[H, 12, 12] hinge blocks c (∇θ∇θᵀ + (θ − θ̄) ∇²θ), c = 2 κb w_e.

    mode: BENDING_EXACT; BENDING_EIGEN (eigenvalues clamped at 0); BENDING_GAUSS_NEWTON
    (c ∇θ∇θᵀ only: PSD by construction, no eigendecomposition). ∇²θ is the complex-step
    derivative of the closed-form gradient, as in energies.dihedral_angle_hessian.
    """
    nh = hinges.shape[0]
    out = np.empty((nh, 12, 12))
    X = np.empty((4, 3))  # scratch, overwritten for each hinge (allocated once)
    g = np.empty(12)
    for h in range(nh):
        for a in range(4):
            for i in range(3):
                X[a, i] = x[hinges[h, a], i]
        if _degenerate(X):
            out[h] = 0.0
            continue
        _angle_gradient_real(X, g)
        c = 2.0 * scale * weight[h]
        for i in range(12):
            for j in range(12):
                out[h, i, j] = c * g[i] * g[j]
        if mode == BENDING_GAUSS_NEWTON:
            continue
        d = _angle(X) - rest_angle[h]
        Z = np.empty((4, 3), dtype=np.complex128)
        gz = np.empty(12, dtype=np.complex128)
        Hd = np.empty((12, 12))
        for j in range(12):
            for a in range(4):
                for i in range(3):
                    Z[a, i] = X[a, i]
            Z[j // 3, j % 3] += 1j * _COMPLEX_STEP
            _angle_gradient(Z, gz)
            for i in range(12):
                Hd[i, j] = gz[i].imag / _COMPLEX_STEP
        for i in range(12):
            for j in range(12):
                out[h, i, j] += c * d * 0.5 * (Hd[i, j] + Hd[j, i])
        if mode == BENDING_EIGEN:
            K = out[h].copy()
            Q = np.empty((12, 12))
            _project_psd(K, 12, Q)
            out[h] = K
    return out


# the assembly and CG kernels live in _assembly_kernels (this module stays under 600 lines)
from ._assembly_kernels import (_csr_find, _element_dofs, cg_direction, cg_step, csr_slots, dot,  # noqa: E402,F401
                                element_keys, element_slots, scatter_add)
