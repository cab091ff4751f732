"""(C + Lambda + sigma I)^{-1} without forming C: one sparse LU of a bordered system.

C + Lambda + sigma I is the Schur complement, over the translations, of the sparse matrix

    K = [[C0 + Lambda + sigma I, B], [B^T, S]]      ((M d + M) square, patch-graph pattern)

so solving K [x; y] = [r; 0] (patch 0's translation grounded: the gauge) gives
x = (C + Lambda + sigma I)^{-1} r. It preconditions every iterative solve near the
solution: LOBPCG for the smallest eigenvectors of C (spectral start) and of C + Lambda
(certificate), and CG for the Newton systems (whose quadratic form on tangent vectors
is <xi, (C + Lambda) xi>).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from mvreg.solver import pardiso
from mvreg.solver.krylov import dense_factor, fill_density

# Above this many unknowns the sparse LU is not attempted (fill-in grows superlinearly;
# measurements behind these limits: docs/design/solver.md).
DIRECT_MAX_UNKNOWNS = 800_000
# The same with MKL PARDISO.
PARDISO_MAX_UNKNOWNS = 2_000_000
NEWTON_PARDISO_MAX_UNKNOWNS = 1_000_000
# A factorization forecast to take more floating-point operations than this is not
# attempted (direct_feasible). PARDISO factorizes at ~10 GFLOP/s on one core of this
# machine (random graph, M = 3000: 3.8e10 in 3.7 s), so ~50 s per factorization, and a run
# takes three (spectrum, polish, certificate). Forecasts at 1% noise: geometric overlap
# graph M = 10k 2.6e9, 30k 2.3e10, 100k 2.7e11 (direct, as before); random (expander)
# graph M = 1000 1.5e9, 3000 3.8e10, 10k 1.4e12 (~3 x 140 s: iterative instead).
FACTOR_MAX_FLOPS = 5e11
# The shift sigma of every shifted inverse (C + Lambda + sigma I)^{-1}, relative to
# lambda_max(C): spectral start, certificate and the large-problem Newton preconditioner.
SHIFT = 1e-4


def patch_order(S: sp.spmatrix) -> np.ndarray | None:
    """Nested-dissection order of the patch graph (METIS via pymetis), or None."""
    try:
        import pymetis
    except ImportError:
        return None
    a = S.tocsr().copy()
    a.setdiag(0)
    a.eliminate_zeros()
    if a.nnz == 0:
        return None
    adj = pymetis.CSRAdjacency(a.indptr.astype(np.int64), a.indices.astype(np.int64))
    perm, _ = pymetis.nested_dissection(adj)
    return np.asarray(perm, dtype=np.int64)


def factorize(K: sp.spmatrix, dof_patch: np.ndarray, S: sp.spmatrix):
    """Sparse factorization of the symmetric K whose unknown u belongs to patch dof_patch[u].

    MKL PARDISO (supernodal LDL^T, METIS order) when available (pardiso.py). Otherwise
    SciPy's SuperLU, with unknowns ordered patch by patch in the nested-dissection order of
    the patch graph (fill grows like a 3-D mesh's instead of a random graph's); without
    pymetis SuperLU's COLAMD is used. Returns solve(b) for b of shape (len,) or (len, r).
    """
    if pardiso.available():
        return pardiso.PardisoFactor(K)
    K = K.tocsc()
    order = patch_order(S)
    if order is None:
        return _Solve(spla.splu(K, permc_spec="COLAMD").solve)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    perm = np.argsort(rank[dof_patch], kind="stable")
    lu = spla.splu(
        K[perm][:, perm].tocsc(),
        permc_spec="NATURAL",
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )

    def solve(b):
        x = np.empty_like(b)
        x[perm] = lu.solve(np.ascontiguousarray(b[perm]))
        return x

    return _Solve(solve)


class _Solve:
    """A solve function without inertia information (SuperLU)."""

    inertia = None

    def __init__(self, fn):
        self._fn = fn

    def __call__(self, b):
        return self._fn(b)


def bordered_system(op, lam_blocks: np.ndarray | None, sigma: float):
    """(K with patch 0's translation grounded, the kept unknowns, their patches)."""
    m, n = op.M, op.n
    a = op.C0 + sigma * sp.eye(n)
    if lam_blocks is not None:
        a = a + sp.block_diag(list(lam_blocks), format="csr")
    K = sp.bmat([[a, op.B], [op.B.T, op.S]], format="csr")
    keep = np.r_[np.arange(n), n + 1 + np.arange(m - 1)]  # translation of patch 0 = 0
    dof_patch = np.r_[np.arange(n) // op.d, np.arange(m)][keep]
    return K[keep][:, keep], keep, dof_patch


class ShiftedInverse:
    """Applies (C + Lambda + sigma I)^{-1} via a sparse LU of the bordered system."""

    def __init__(self, op, lam_blocks: np.ndarray | None, sigma: float):
        K, self.keep, dof_patch = bordered_system(op, lam_blocks, sigma)
        self.n, self.m = op.n, op.M
        self._solve = factorize(K, dof_patch, op.S)

    @property
    def negative_eigenvalues(self) -> int | None:
        """Number of eigenvalues of C + Lambda + sigma I below 0, when the factor tells.

        K's inertia is the translations' Laplacian block's (M - 1 positive) plus that of its
        Schur complement C + Lambda + sigma I (Haynsworth), so K's negative pivot count is
        the count for C + Lambda + sigma I. None with SuperLU or perturbed pivots.
        """
        f = self._solve
        if f.inertia is None or getattr(f, "perturbed", 0):
            return None
        return int(f.inertia[1])

    def __call__(self, r: np.ndarray) -> np.ndarray:
        r2 = r[:, None] if r.ndim == 1 else r
        rhs = np.zeros((self.n + self.m, r2.shape[1]))
        rhs[: self.n] = r2
        sol = np.zeros_like(rhs)
        sol[self.keep] = self._solve(np.ascontiguousarray(rhs[self.keep]))
        out = sol[: self.n]
        return out[:, 0] if r.ndim == 1 else out


def newton_direct_feasible(op) -> bool:
    """Whether the exact Newton system (d(d-1)/2 + d unknowns per patch) is worth factorizing.

    Above this size the Newton CG is preconditioned by the cheaper (C + Lambda + sigma I)^{-1}
    of the (d + 1)-unknowns-per-patch bordered system instead (docs/design/solver.md).
    """
    if not direct_feasible(op):
        return False
    k = op.d * (op.d - 1) // 2
    limit = NEWTON_PARDISO_MAX_UNKNOWNS if pardiso.available() else DIRECT_MAX_UNKNOWNS
    return op.M * (k + op.d) <= limit


def direct_feasible(op) -> bool:
    """Whether a sparse factorization of the bordered system is affordable for this problem.

    Its size first (``PARDISO_MAX_UNKNOWNS`` / ``DIRECT_MAX_UNKNOWNS``); with PARDISO also
    its cost, forecast once per operator by PARDISO's analysis (METIS ordering and symbolic
    factorization, no numbers): at most ``FACTOR_MAX_FLOPS``. The fill of a factorization
    depends on the overlap graph, not on its size alone: a graph like a mesh (scans of an
    object, a building) has small separators, an expander (random overlaps) has none, and
    its factor is nearly dense. The iterative paths (LOBPCG and CG without a factorization)
    converge fast exactly there, since an expander's spectrum is well separated.
    """
    limit = PARDISO_MAX_UNKNOWNS if pardiso.available() else DIRECT_MAX_UNKNOWNS
    if op.M * (op.d + 1) > limit:
        return False
    if not pardiso.available() or op.M < 2:
        return True
    if op.factor_forecast is None:
        t0 = time.perf_counter()
        K, _, _ = bordered_system(op, None, 1.0)
        f = pardiso.PardisoFactor(K, analyse_only=True)
        op.factor_forecast = {
            "factor_nnz": f.factor_nnz,
            "factor_flops": f.factor_flops,
            "fill": fill_density(f.factor_nnz, K.shape[0]),
            "dense": dense_factor(f.factor_nnz, K.shape[0], f.factor_flops),
            "direct": bool(f.factor_flops <= FACTOR_MAX_FLOPS),
        }
        op.timings["factor_forecast"] = time.perf_counter() - t0
    return op.factor_forecast["direct"]


def krylov_first(op) -> bool:
    """Whether to try the factorization-free path first where a factorization is affordable:
    PARDISO forecasts a nearly dense factor of the bordered system (krylov.dense_factor,
    an expander-like overlap graph). False without PARDISO's forecast."""
    if not direct_feasible(op) or op.factor_forecast is None:
        return False
    return bool(op.factor_forecast.get("dense", False))


def skew_basis(d: int) -> np.ndarray:
    """(k, d, d) basis E_a of skew matrices: [w]_x for d = 3, [[0,-1],[1,0]] for d = 2."""
    if d == 2:
        return np.array([[[0.0, -1.0], [1.0, 0.0]]])
    e = np.zeros((3, 3, 3))
    e[0, 2, 1], e[0, 1, 2] = 1.0, -1.0
    e[1, 0, 2], e[1, 2, 0] = 1.0, -1.0
    e[2, 1, 0], e[2, 0, 1] = 1.0, -1.0
    return e


def tangent_jacobian(X: np.ndarray, d: int) -> sp.csr_matrix:
    """Sparse J (d n, M k): omega -> vec(xi) with xi_i = X_i sum_a omega_ia E_a.

    vec stacks the d columns of xi (n each): row c n + i d + r holds xi[i d + r, c].
    """
    n = X.shape[0]
    m = n // d
    e = skew_basis(d)
    k = e.shape[0]
    vals = np.einsum("mrb,abc->marc", X.reshape(m, d, d), e)  # (M, k, r, c)
    i, a, r, c = np.meshgrid(np.arange(m), np.arange(k), np.arange(d), np.arange(d), indexing="ij")
    rows = c * n + i * d + r
    cols = i * k + a
    return sp.csr_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(d * n, m * k))


class NewtonSystem:
    """The exact Riemannian Newton system at X, as one sparse LU.

    The Hessian of f(X) = Tr(X^T C X) on O(d)^M is the Schur complement, over the
    translations, of a sparse matrix with the pattern of the patch graph:

        [ J^T (I_d (x) C0) J - Q     J^T (I_d (x) B) ] [omega]   [-J^T vec(g)]
        [ (I_d (x) B^T) J            I_d (x) S        ] [tau  ] = [ 0         ]

    with xi_i = X_i [omega_i] (k = d(d-1)/2 tangent coordinates per patch), J the map
    omega -> vec(xi), Q_i[a, b] = tr(E_a^T E_b M_i) the curvature term and g = (C + Lambda) X.
    Patch 0 is grounded (omega_0 = 0, tau_0 = 0: the gauge). ``step(g)`` returns
    -Hess^{-1} g as an (n, d) tangent matrix; used as CG preconditioner away from X.
    """

    def __init__(self, op, X: np.ndarray, CX: np.ndarray):
        d, m, n = op.d, op.M, op.n
        e = skew_basis(d)
        k = e.shape[0]
        self.d, self.m, self.n, self.k = d, m, n, k
        xb = X.reshape(m, d, d)
        mi = np.einsum("mba,mbc->mac", xb, CX.reshape(m, d, d))
        mi = 0.5 * (mi + mi.transpose(0, 2, 1))
        J = tangent_jacobian(X, d)
        self.J = J
        c0d = sp.block_diag([op.C0] * d, format="csr")
        bd = sp.block_diag([op.B] * d, format="csr")
        q = np.einsum("axy,bxz,myz->mab", e, e, mi)
        q = 0.5 * (q + q.transpose(0, 2, 1))
        h_ww = (J.T @ c0d @ J - sp.block_diag(list(q), format="csr")).tocsr()
        h_wt = (J.T @ bd).tocsr()
        h_tt = sp.block_diag([op.S] * d, format="csr")
        K = sp.bmat([[h_ww, h_wt], [h_wt.T, h_tt]], format="csr")
        drop = np.r_[np.arange(k), m * k + np.arange(d) * m]  # omega_0, tau_0
        self.keep = np.setdiff1d(np.arange(K.shape[0]), drop)
        dof_patch = np.r_[np.arange(m * k) // k, np.tile(np.arange(m), d)][self.keep]
        self._solve = factorize(K[self.keep][:, self.keep], dof_patch, op.S)

    def step(self, g: np.ndarray) -> np.ndarray:
        """Newton direction (n, d) for the Riemannian gradient g (n, d)."""
        rhs = np.zeros(self.m * (self.k + self.d))
        rhs[: self.m * self.k] = -(self.J.T @ g.T.reshape(-1))
        sol = np.zeros_like(rhs)
        sol[self.keep] = self._solve(rhs[self.keep])
        return (self.J @ sol[: self.m * self.k]).reshape(self.d, self.n).T
