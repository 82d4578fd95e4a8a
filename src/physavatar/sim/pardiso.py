"""Sparse Cholesky by Intel MKL PARDISO (the optional ``mkl`` extra), called through ctypes.

cholespy, the default, ships a reference BLAS (``cholespy.libs``), so its supernodal
factorisation runs its dense blocks at reference-BLAS speed: on the large case of
``benchmarks/sim_speed.py`` (45k DOFs, a 0.94M-nonzero preconditioner matrix, 4M nonzeros in
its factor) one factorisation took 476 ms against 46 ms for PARDISO's numeric phase on the
same core (docs/simulation.md "Session 21"). PARDISO also splits the work into a symbolic
phase (METIS ordering, 11) and a numeric one (22), so the Newton solver's refactorisations of
matrices with one fixed pattern pay only the numeric phase.

MKL is a ~220 MB wheel (with intel-openmp and tbb ~700 MB installed), hence an optional extra
(``pip install physavatar[mkl]``; ``scripts/setup_env.sh`` installs it): without it
:func:`available` is False and ``assembly.Factorization`` uses cholespy as before. ``mkl_rt``
is the file ``PHYSAVATAR_MKL_RT`` names, else the environment's ``lib/libmkl_rt.so*`` (where the
wheel puts it), else the loader's.

The routine is MKL's ``pardiso`` (real symmetric positive definite, ``mtype`` 2, upper
triangle in zero-based CSR). ctypes releases the GIL for the call. Threads: per factor
(``SimSettings.solver_threads``, default 1: a shared machine's other core is left alone), on
MKL's GNU OpenMP layer (the runtime torch and numba use; MKL's own Intel runtime beside it
crashed), or sequential where libgomp cannot be loaded.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import glob
import os
import sys

import numpy as np
import scipy.sparse as sp

_MTYPE_SPD = 2
_ONE = ctypes.byref(ctypes.c_int32(1))  # maxfct, mnum
_MTYPE = ctypes.byref(ctypes.c_int32(_MTYPE_SPD))
_ZERO = ctypes.byref(ctypes.c_int32(0))  # msglvl
_LIB = None  # the loaded mkl_rt, or False when it cannot be loaded


def _candidates():
    env = os.environ.get("PHYSAVATAR_MKL_RT")
    if env:
        yield env
    for prefix in dict.fromkeys((sys.prefix, sys.base_prefix)):
        yield from sorted(glob.glob(os.path.join(prefix, "lib", "libmkl_rt.so*")), key=len)
    found = ctypes.util.find_library("mkl_rt")
    if found:
        yield found


_INTEL, _SEQUENTIAL, _GNU = 0, 1, 3  # MKL_THREADING_*
_GOMP = None


def _load_gomp() -> bool:
    """libgomp with its symbols global (MKL's GNU threading layer resolves them from there)."""
    global _GOMP
    if _GOMP is None:
        try:
            _GOMP = ctypes.CDLL(ctypes.util.find_library("gomp") or "libgomp.so.1", mode=ctypes.RTLD_GLOBAL)
        except OSError:
            _GOMP = False
    return bool(_GOMP)


def _lib():
    global _LIB
    if _LIB is None:
        _LIB = False
        for path in _candidates():
            try:
                lib = ctypes.CDLL(path)
                lib.pardiso.restype = None
                lib.MKL_Set_Threading_Layer.argtypes = [ctypes.c_int]
                # (before any MKL call) GNU OpenMP, the runtime torch and numba load too: MKL's
                # own (Intel) runtime beside torch's libgomp crashed in the first threaded
                # factorisation; without libgomp, sequential (one thread whatever is asked)
                lib.MKL_Set_Threading_Layer(_GNU if _load_gomp() else _SEQUENTIAL)
                lib.MKL_Domain_Set_Num_Threads.argtypes = [ctypes.c_int, ctypes.c_int]
                _LIB = lib
                break
            except (OSError, AttributeError):
                continue
    return _LIB or None


def available() -> bool:
    """True when MKL's runtime library (``mkl_rt``) can be loaded."""
    return _lib() is not None


def _same_buffer(a: np.ndarray, b: np.ndarray) -> bool:
    """a is b, or a view of the same memory with the same layout (scipy's csr constructor
    may keep a view of the index arrays it is given). ``b`` is held by the factor, so its
    memory cannot have been reused by another array; a pattern array changed in place is not
    supported."""
    return a is b or (a.ctypes.data == b.ctypes.data and a.shape == b.shape and a.strides == b.strides
                      and a.dtype == b.dtype)


def same_or_equal(a: np.ndarray, b: np.ndarray) -> bool:
    """np.array_equal(a, b), without reading them when they are the same memory."""
    return _same_buffer(a, b) or np.array_equal(a, b)


class PardisoError(RuntimeError):
    pass


class PardisoCholesky:
    """Cholesky factor of a symmetric positive-definite sparse matrix (MKL PARDISO).

    ``reuse``: an earlier factor of a matrix with the same pattern. With ``move=True`` its
    PARDISO handle (symbolic analysis and memory) is taken over and only the numeric phase
    runs; ``reuse`` cannot solve afterwards (its owner must not hold on to it). With
    ``move=False`` a new handle is made with ``reuse``'s fill-reducing permutation (no METIS
    run). Without ``reuse``, or with another pattern, a full analysis.

    Raises PardisoError when the matrix is not positive definite (a zero or negative pivot),
    ValueError when MKL is not available or the matrix has an unstored diagonal entry.
    """

    def __init__(self, M, reuse: "PardisoCholesky | None" = None, move: bool = False, threads: int = 1):
        self.threads = max(1, int(threads))
        lib = _lib()
        if lib is None:
            raise ValueError("MKL (mkl_rt) is not available: pip install 'physavatar[mkl]'")
        M = M if sp.isspmatrix_csr(M) else sp.csr_matrix(M)
        if (reuse is not None and reuse._src is not None and _same_buffer(M.indptr, reuse._src[0])
                and _same_buffer(M.indices, reuse._src[1]) and M.has_canonical_format):
            # the pattern arrays of reuse's matrix (the Newton solver's fixed patterns; scipy
            # keeps them or views of them): the upper triangle is a gather of the values, the
            # pattern is reuse's
            self.n, self.indptr, self.indices = reuse.n, reuse.indptr, reuse.indices
            self._src, self._upper = reuse._src, reuse._upper
            self.data = M.data[self._upper]
            same = True
        else:
            self._upper_triangle(M)
            same = (reuse is not None and reuse.n == self.n and np.array_equal(reuse.indptr, self.indptr)
                    and np.array_equal(reuse.indices, self.indices))
        self._err = ctypes.c_int32(0)
        self._n = ctypes.c_int32(self.n)
        if same and move and reuse._pt is not None:
            self._pt, self.iparm, self.perm = reuse._pt, reuse.iparm, reuse.perm
            reuse._pt = None  # moved
            self._call(22)
            return
        self._pt = np.zeros(64, dtype=np.int64)
        ip = self.iparm = np.zeros(64, dtype=np.int32)
        ip[0] = 1  # iparm set here (0-based below; MKL's documentation counts from 1)
        ip[1] = 2  # METIS nested dissection
        ip[9] = 8  # pivot perturbation 1e-8 (not used by a positive-definite factorisation)
        ip[34] = 1  # zero-based indices
        if same:
            self.perm = reuse.perm.copy()
            ip[4] = 1  # the user's permutation
        else:
            self.perm = np.zeros(self.n, dtype=np.int32)
            ip[4] = 2  # return METIS's permutation in perm
        try:
            self._call(12)
        except PardisoError:
            self.free()
            raise
        ip[4] = 1  # later analyses with this perm (move=False) skip METIS

    def _upper_triangle(self, M):
        """self.indptr / indices / data: M's upper triangle in canonical zero-based CSR (int32
        indices, as PARDISO takes them). For a canonical M (sorted, no duplicates) the values
        are a gather (``_upper``, kept with M's pattern arrays in ``_src``: a later matrix with
        the same arrays gathers its values the same way); the same values in the same order as
        ``sp.triu`` + ``sum_duplicates``, the general path."""
        self.n = int(M.shape[0])
        self._src = self._upper = None
        if M.has_canonical_format:
            row = np.repeat(np.arange(self.n, dtype=np.int32), np.diff(M.indptr))
            upper = np.flatnonzero(M.indices >= row)
            self.indptr = np.r_[0, np.cumsum(np.bincount(row[upper], minlength=self.n))].astype(np.int32)
            self.indices = M.indices[upper].astype(np.int32)
            self.data = np.ascontiguousarray(M.data[upper], dtype=np.float64)
            self._src, self._upper = (M.indptr, M.indices), upper
        else:
            U = sp.triu(M, format="csr")
            U.sum_duplicates()  # canonical: sorted indices, no duplicates
            self.indptr = U.indptr.astype(np.int32)
            self.indices = U.indices.astype(np.int32)
            self.data = np.ascontiguousarray(U.data, dtype=np.float64)
        if self.n and np.any(self.indices[self.indptr[:-1]] != np.arange(self.n)):
            raise ValueError("PARDISO needs every diagonal entry stored")

    def _call(self, phase, b=None, x=None, nrhs=1):
        lib = _lib()
        lib.MKL_Domain_Set_Num_Threads(self.threads, 4)  # MKL_DOMAIN_PARDISO
        err = self._err
        err.value = 0
        vp = ctypes.c_void_p
        lib.pardiso(vp(self._pt.ctypes.data), _ONE, _ONE, _MTYPE, ctypes.byref(ctypes.c_int32(phase)),
                    ctypes.byref(self._n), vp(self.data.ctypes.data), vp(self.indptr.ctypes.data),
                    vp(self.indices.ctypes.data), vp(self.perm.ctypes.data), ctypes.byref(ctypes.c_int32(nrhs)),
                    vp(self.iparm.ctypes.data), _ZERO, None if b is None else vp(b.ctypes.data),
                    None if x is None else vp(x.ctypes.data), ctypes.byref(err))
        if err.value != 0:
            raise PardisoError(f"MKL PARDISO phase {phase} failed with error {err.value}"
                               + (" (not positive definite)" if err.value == -4 else ""))

    def solve(self, b: np.ndarray) -> np.ndarray:
        """b: [n] or [n, k] (columns solved together)."""
        if self._pt is None:
            raise RuntimeError("this PARDISO factor was refactorised in place (moved)")
        b = np.asarray(b, dtype=np.float64)
        nrhs = 1 if b.ndim == 1 else b.shape[1]
        bf = np.asfortranarray(b)
        x = np.empty_like(bf)
        self._call(33, bf, x, nrhs)
        return np.ascontiguousarray(x)

    def free(self):
        if getattr(self, "_pt", None) is not None and _LIB:
            try:
                self._call(-1)
            except Exception:  # noqa: BLE001 - freeing at shutdown must not raise
                pass
        self._pt = None

    def __del__(self):
        self.free()
