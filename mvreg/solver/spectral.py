"""Spectral (eigenvector) estimator, paper 001 section 2, for d x d blocks; the spectrum of C.

``spectrum(op, dense, seed)``: the d+1 smallest eigenpairs of C and an upper bound on
lambda_max(C) (exact when dense, 1.01 x the Lanczos estimate matrix-free), as a Spectrum.
``spectral_rotations(spec, d)``: the d eigenvectors of the d smallest eigenvalues, scaled
by sqrt(M) and rounded blockwise to SO(d) / O(d) (a global reflection is a gauge).

As a registered solver (``run``): the start rotations, which ``solve()`` computes this way
by default; no iterations, no history. solve() then certifies them (and Newton-polishes
them first with ``solve.spectral.polish``).
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from mvreg.solver.base import SolverContext, SolverRun, Spectrum
from mvreg.solver.blocks import round_to_rotations
from mvreg.solver.shift_invert import SHIFT, ShiftedInverse, direct_feasible

__all__ = ["Spectrum", "lambda_max", "run", "spectral_rotations", "spectrum"]


def lambda_max(op, dense: bool, seed: int = 0) -> float:
    if dense:
        c = op.dense()
        return float(sla.eigh(c, eigvals_only=True, subset_by_index=[op.n - 1, op.n - 1])[0])
    v0 = np.random.default_rng(seed).standard_normal(op.n)
    val = spla.eigsh(op.as_linear_operator(), k=1, which="LA", tol=1e-3, v0=v0)[0][0]
    return float(val) * 1.01  # Lanczos under-estimates; a safe upper bound is needed


def spectrum(op, dense: bool, seed: int = 0, tol: float = 1e-10) -> Spectrum:
    """Smallest d+1 eigenpairs of C.

    Dense: exact eigh. Matrix-free: shift-invert Lanczos with (C + sigma I)^{-1} from one
    sparse LU (shift_invert.py) when affordable, else LOBPCG preconditioned by the inverse
    diagonal blocks of C0 (Lanczos on lambda_max I - C, slow when lambda_{d+1} /
    lambda_max is small, if LOBPCG breaks down).
    """
    d, n = op.d, op.n
    k = min(d + 1, n)
    if dense:
        c = op.dense()
        w, v = sla.eigh(c, subset_by_index=[0, k - 1])
        lmax = lambda_max(op, True)
        return Spectrum(w, v, lmax)
    lmax = lambda_max(op, False, seed)
    if direct_feasible(op):
        # Shift-invert with the exact (C + sigma I)^{-1} from one sparse factorization.
        sigma = SHIFT * lmax
        inv = ShiftedInverse(op, None, sigma)
        opinv = spla.LinearOperator((n, n), matvec=inv, matmat=inv, dtype=np.float64)
        v0 = np.random.default_rng(seed).standard_normal(n)
        w, v = spla.eigsh(
            op.as_linear_operator(), k=k, sigma=-sigma, OPinv=opinv, which="LM", tol=tol, v0=v0
        )
        order = np.argsort(w)
        return Spectrum(w[order], v[:, order], lmax)
    try:
        return lobpcg_spectrum(op, k, lmax, seed)
    except (np.linalg.LinAlgError, ValueError):
        pass  # LOBPCG broke down (a singular block): Lanczos, slower but sure
    shifted = spla.LinearOperator(
        (n, n), matvec=lambda x: lmax * x - op.matvec(x), dtype=np.float64
    )
    v0 = np.random.default_rng(seed).standard_normal(n)
    w, v = spla.eigsh(shifted, k=k, which="LA", tol=tol, v0=v0, ncv=max(4 * k, 20))
    w = lmax - w
    order = np.argsort(w)
    return Spectrum(w[order], v[:, order], lmax)


def block_jacobi(op) -> spla.LinearOperator:
    """The inverse of the d x d diagonal blocks of C0 (the data's own blocks) as an
    operator: LOBPCG's preconditioner where no factorization is affordable."""
    d, m = op.d, op.M
    blocks = op.diagonal_blocks()
    ridge = 1e-12 * np.maximum(np.trace(blocks, axis1=1, axis2=2), 1e-300)
    inv = np.linalg.inv(blocks + ridge[:, None, None] * np.eye(d))

    def apply(x):
        x2 = x.reshape(m, d, -1)
        return np.einsum("mab,mbr->mar", inv, x2).reshape(x.shape)

    return spla.LinearOperator((op.n, op.n), matvec=apply, matmat=apply, dtype=np.float64)


# LOBPCG's iteration cap and tolerance (residual norm relative to lambda_max) for the
# spectrum without a factorization. The vectors start the solver, which polishes and
# certifies them, so a few digits suffice (random graph, M = 3000: 200 iterations give
# lambda_{d+1} to 1%, M = 10k: see docs/benchmarks/noise_sweep.md).
LOBPCG_MAX_ITER = 400
LOBPCG_RTOL = 1e-6


def lobpcg_spectrum(op, k: int, lmax: float, seed: int) -> Spectrum:
    """The k smallest eigenpairs of C by LOBPCG, block-Jacobi preconditioned."""
    x0 = np.random.default_rng(seed).standard_normal((op.n, k))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "did not reach the tolerance"
        w, v = spla.lobpcg(
            op.as_linear_operator(), x0, M=block_jacobi(op), largest=False,
            tol=LOBPCG_RTOL * lmax, maxiter=LOBPCG_MAX_ITER,
        )  # fmt: skip
    order = np.argsort(w)
    return Spectrum(np.asarray(w)[order], np.asarray(v)[:, order], lmax)


def spectral_rotations(spec: Spectrum, d: int, allow_reflections: bool = False) -> np.ndarray:
    """Round the d smallest eigenvectors to rotations (M, d, d)."""
    n = spec.vectors.shape[0]
    m = n // d
    return round_to_rotations(np.sqrt(m) * spec.vectors[:, :d], d, allow_reflections)


def run(ctx: SolverContext) -> SolverRun:
    """Registry entry "spectral": the start rotations themselves (spectral by default)."""
    return SolverRun(rotations=ctx.start, iterations=0, converged=True)
