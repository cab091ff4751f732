"""Intel MKL PARDISO for the symmetric sparse systems of the solver (ctypes, no extra wrapper).

PARDISO is a supernodal, multithreaded direct solver with METIS ordering; on the bordered
systems of shift_invert.py it factorizes much faster than SciPy's SuperLU (measurements:
docs/design/solver.md). It is used when MKL's runtime library (the ``mkl`` wheel on x86-64)
can be loaded; otherwise the solver falls back to SuperLU. ``available()`` says which;
``disabled()`` forces the fallback within a block.

Matrices are factorized as real symmetric indefinite (mtype -2, Bunch-Kaufman pivoting), so
the same code serves the positive definite shift-invert systems and the Newton systems,
which may be indefinite away from a minimum. The factorization also reports the inertia.
"""

from __future__ import annotations

import ctypes
import glob
import os
import site
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from ctypes.util import find_library

import numpy as np
import scipy.sparse as sp

from mvreg.errors import SolverError

_LIB: ctypes.CDLL | None = None
_TRIED = False
MTYPE_SYMMETRIC_INDEFINITE = -2


def _load() -> ctypes.CDLL | None:
    global _LIB, _TRIED
    if _TRIED:
        return _LIB
    _TRIED = True
    if os.environ.get("MVREG_NO_PARDISO"):
        return None
    cands = [os.environ.get("MVREG_MKL_RT"), find_library("mkl_rt")]
    for base in (sys.prefix, site.USER_BASE):
        cands += sorted(glob.glob(os.path.join(base, "lib", "libmkl_rt.so*")), key=len)
    for path in cands:
        if not path:
            continue
        try:
            lib = ctypes.CDLL(path)
            lib.pardiso  # noqa: B018 (the symbol must exist)
        except (OSError, AttributeError):
            continue
        p_int = ctypes.POINTER(ctypes.c_int32)
        lib.pardiso.argtypes = [
            ctypes.POINTER(ctypes.c_int64),  # pt
            p_int,  # maxfct
            p_int,  # mnum
            p_int,  # mtype
            p_int,  # phase
            p_int,  # n
            ctypes.c_void_p,  # a
            p_int,  # ia
            p_int,  # ja
            p_int,  # perm
            p_int,  # nrhs
            p_int,  # iparm
            p_int,  # msglvl
            ctypes.c_void_p,  # b
            ctypes.c_void_p,  # x
            p_int,  # error
        ]
        lib.pardiso.restype = None
        _LIB = lib
        break
    return _LIB


def available() -> bool:
    """Whether MKL PARDISO can be loaded on this machine."""
    return _load() is not None


@contextmanager
def disabled() -> Iterator[None]:
    """Within the block PARDISO counts as unavailable (the SuperLU / AMG fallbacks run)."""
    global _LIB, _TRIED
    saved = _LIB, _TRIED
    _LIB, _TRIED = None, True
    try:
        yield
    finally:
        _LIB, _TRIED = saved


class PardisoFactor:
    """LDL^T factorization of a real symmetric sparse matrix; ``solve(b)`` for (n,) or (n, r).

    ``refine``: up to two steps of iterative refinement per solve (accurate to rounding
    errors, at up to three times the cost).

    Attributes: ``inertia`` = (positive, negative) pivot counts (with ``perturbed`` pivots
    replaced by small values: then the counts are approximate); ``factor_nnz``.

    ``analyse_only``: only the analysis (METIS ordering, symbolic factorization): sets
    ``factor_nnz`` and ``factor_flops`` (what the factorization would take) and releases.
    """

    def __init__(self, a: sp.spmatrix, refine: bool = False, *, analyse_only: bool = False):
        lib = _load()
        if lib is None:
            raise SolverError("MKL PARDISO is not available")
        n = a.shape[0]
        up = sp.triu(a, format="coo")
        # PARDISO wants every diagonal entry stored (explicit zeros are fine).
        rows = np.r_[up.row, np.arange(n)]
        cols = np.r_[up.col, np.arange(n)]
        vals = np.r_[up.data, np.zeros(n)]
        u = sp.csr_matrix((vals, (rows, cols)), shape=(n, n))
        u.sum_duplicates()
        u.sort_indices()
        self.n = n
        self._a = np.ascontiguousarray(u.data, dtype=np.float64)
        self._ia = np.ascontiguousarray(u.indptr, dtype=np.int32)
        self._ja = np.ascontiguousarray(u.indices, dtype=np.int32)
        self._pt = np.zeros(64, dtype=np.int64)
        self._iparm = np.zeros(64, dtype=np.int32)
        ip = self._iparm
        ip[0] = 1  # user-supplied iparm
        ip[1] = 2  # METIS nested dissection ordering
        ip[7] = 2  # up to two iterative refinement steps
        ip[9] = 8  # pivot perturbation 1e-8
        ip[10] = 0  # no scaling (symmetric indefinite)
        ip[12] = 0  # no weighted matching
        ip[17] = -1  # report nonzeros of the factor
        ip[18] = -1 if analyse_only else 0  # report the factorization's MFLOP (analysis)
        ip[20] = 1  # Bunch-Kaufman 1x1 and 2x2 pivoting
        ip[34] = 1  # zero-based indexing
        self._alive = True
        if analyse_only:
            self._call(11, np.zeros(n), np.zeros(n), 1)
            self.factor_nnz, self.factor_flops = int(ip[17]), 1e6 * float(ip[18])
            self.release()
            return
        self._call(12, np.zeros(n), np.zeros(n), 1)
        self.factor_nnz = int(ip[17])
        self.inertia = (int(ip[21]), int(ip[22]))
        self.perturbed = int(ip[13])
        # Iterative refinement costs a product and a solve per step: asked for where solves
        # must be accurate to rounding (products with C), or when pivots were perturbed.
        ip[7] = 2 if (refine or self.perturbed) else 0

    def _call(self, phase: int, b: np.ndarray, x: np.ndarray, nrhs: int) -> None:
        err = ctypes.c_int32(0)
        i32 = ctypes.c_int32
        p_int = ctypes.POINTER(i32)
        _LIB.pardiso(
            self._pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
            ctypes.byref(i32(1)),
            ctypes.byref(i32(1)),
            ctypes.byref(i32(MTYPE_SYMMETRIC_INDEFINITE)),
            ctypes.byref(i32(phase)),
            ctypes.byref(i32(self.n)),
            self._a.ctypes.data,
            self._ia.ctypes.data_as(p_int),
            self._ja.ctypes.data_as(p_int),
            None,
            ctypes.byref(i32(nrhs)),
            self._iparm.ctypes.data_as(p_int),
            ctypes.byref(i32(0)),
            b.ctypes.data,
            x.ctypes.data,
            ctypes.byref(err),
        )
        if err.value != 0:
            if phase != -1:
                self.release()
            raise SolverError(f"PARDISO phase {phase} failed with error {err.value}")

    def solve(self, b: np.ndarray) -> np.ndarray:
        if not self._alive:
            raise SolverError("PARDISO factor already released")
        squeeze = b.ndim == 1
        bf = np.asfortranarray(b[:, None] if squeeze else b, dtype=np.float64)
        x = np.zeros_like(bf, order="F")
        self._call(33, bf, x, bf.shape[1])
        return x[:, 0] if squeeze else np.ascontiguousarray(x)

    __call__ = solve

    def release(self) -> None:
        if self._alive:
            self._alive = False
            dummy = np.zeros(1)
            self._call(-1, dummy, dummy, 1)

    def __del__(self):
        try:
            self.release()
        except Exception:  # noqa: BLE001 (interpreter shutdown)
            pass
