"""Krylov paths where a sparse factorization fills in: the fill test and a block Jacobi-PCG.

A sparse direct factorization pays where the overlap graph has small separators (a mesh:
scans of an object or a building); there its factor stays sparse. On an expander (random
overlaps) every separator is a constant fraction of the graph and the factor is nearly
dense: O(n^2) memory, O(n^3) work, and every triangular solve costs a dense product. PARDISO's
analysis (METIS ordering and symbolic factorization, no numbers) forecasts the factor's
nonzeros; ``dense_factor`` reads them. Where the factor is dense the solver tries the
Krylov paths first (preconditioned CG on the Laplacian, block-Jacobi CG in the Newton
polish) and factorizes only when they do not converge within their budgets; elsewhere it
factorizes as before. Design notes: docs/design/solver_expander.md.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

# A factor with at least this fraction of a dense triangle's entries is "dense". Measured
# (PARDISO analysis of the bordered system, d = 3, degree 6): random overlap graph 0.23
# (M = 300), 0.19 (1,000), 0.18 (3,000); geometric graph 0.069 (300), 0.033 (1,000),
# 0.0067 (10,000), falling with M as a mesh's separators do.
DENSE_FILL = 0.1
# ... and forecast to take at least this many flops: a cheaper factorization (~10 ms at
# PARDISO's ~10 GFLOP/s on one core) costs less than the Krylov paths' trial.
KRYLOV_MIN_FLOPS = 1e8


def fill_density(factor_nnz: int, n: int) -> float:
    """Nonzeros of a factor of an n x n matrix over those of a dense triangle."""
    return float(factor_nnz) / max(n * (n + 1) / 2.0, 1.0)


def dense_factor(factor_nnz: int, n: int, factor_flops: float) -> bool:
    """Whether a factor of an n x n matrix with ``factor_nnz`` nonzeros is nearly dense and
    costly (the Krylov paths go first)."""
    return fill_density(factor_nnz, n) >= DENSE_FILL and factor_flops >= KRYLOV_MIN_FLOPS


def laplacian_pcg(
    S: sp.csr_matrix, b: np.ndarray, rtol: float = 1e-15, maxiter: int = 400
) -> tuple[np.ndarray, int, bool]:
    """Solve S x = b for a connected graph Laplacian S and mean-free columns b (M, r).

    Conjugate gradients on the singular, consistent system (the iterates stay in the range
    of S up to the constant vector, removed at the end), Jacobi-preconditioned, all columns
    at once. Converges at the rate set by S's spectral gap: ~40 iterations to 1e-15 on a
    degree-6 random graph of any size, slowly on a mesh (where the factor is cheap anyway).
    Returns (mean-free x, iterations, converged: every column's residual <= rtol ||b||,
    or stalled within 100 rtol at the rounding floor).
    """
    # Work on the transposes (r, M): elementwise operations on (M, r) arrays with few
    # columns run several times slower (inner loops of length r).
    dinv = 1.0 / np.maximum(S.diagonal(), 1e-300)
    bt = np.ascontiguousarray((b - b.mean(axis=0, keepdims=True)).T)
    x = np.zeros_like(bt)
    r = bt.copy()
    z = dinv * r
    p = z.copy()
    rz = np.einsum("ij,ij->i", r, z)
    nb2 = np.einsum("ij,ij->i", bt, bt)
    target = rtol**2 * nb2
    best = np.full_like(nb2, np.inf)
    since_best = its = 0
    rr = nb2
    q = np.empty_like(bt)
    while its < maxiter:
        its += 1
        for i in range(len(q)):  # one sparse product per column: faster than a block
            q[i] = S @ p[i]
        pq = np.einsum("ij,ij->i", p, q)
        alpha = np.divide(rz, pq, out=np.zeros_like(rz), where=pq > 0)[:, None]
        x += alpha * p
        r -= alpha * q
        rr = np.einsum("ij,ij->i", r, r)
        if np.all(rr <= target):
            break
        improved = rr < 0.5 * best
        best = np.where(improved, rr, best)
        since_best = 0 if np.any(improved) else since_best + 1
        if since_best >= 20:
            break  # rounding floor
        z = dinv * r
        rz_new = np.einsum("ij,ij->i", r, z)
        beta = np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz > 0)[:, None]
        p = z + beta * p
        rz = rz_new
    converged = bool(np.all(rr <= 1e4 * target))
    x = x.T - x.mean(axis=1)
    return np.ascontiguousarray(x), its, converged
