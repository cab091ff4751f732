"""Generalized power method (GPM), paper 001 Algorithm 1, for d x d orthogonal blocks.

Paper 001 maximizes x^* C x over unit-modulus vectors with x <- P((C + alpha I) x).
Here the problem is ``min Tr(C O^T O)`` over O = [R_1 .. R_M] with R_i in SO(d) (or O(d)),
which on the feasible set (Tr(O O^T) = M d is constant) is the same as maximizing
``Tr(X^T (alpha I - C) X)`` with X = O^T. One iteration:

    Y = (alpha I - C) X              (one product with C, matrix-free via op.matvec)
    X_i <- argmax_{Q in SO(d) / O(d)} Tr(Q^T Y_i)     (blockwise SVD projection)

Inertia: alpha = ctx.spectrum.largest, an upper bound on lambda_max(C) (exact in the dense
path, 1.01 x the Lanczos estimate matrix-free), so alpha I - C is PSD. Then the cost is
non-increasing (paper 001 Lemma 7): g(X) = Tr(X^T (alpha I - C) X) is convex, so
g(X+) >= g(X) + 2 Tr((X+ - X)^T Y) >= g(X), because X+ maximizes Tr(X+^T Y) blockwise
(also over SO(d)). Since Tr(X^T X) = Md, f = alpha Md - g decreases.

Stopping rule (documented; checked every iteration):
    * relative cost decrease (f_k - f_{k+1}) / (alpha M d) <= tol, and
    * block change ||X_{k+1} - X_k||_F / sqrt(M d) <= tol,
  or the iteration cap ``max_iter``. The fixed-point gap of paper 001 Sec. 5
  (1 - Tr(X^T Y) / sum_i ||Y_i||_*, zero exactly at fixed points of the iteration) is
  recorded in the history for reference.

Options: ``solve.gpm`` (GpmOptions: max_iter, tol, polish). Iteration records: the
objective f in the problem's units; primal_residual 0 (every iterate is feasible);
dual_residual the block change; rho None; extra: relative_decrease, block_change,
fixed_point_gap.

Accuracy: the certificate (solve()) bounds the suboptimality by ~||grad||^2 / mu, so on
noisy data a KKT residual of ~1e-6 (what tol = 1e-6 gives) is often too inexact to be
certified although the point is the global optimum; tol ~1e-9 (used in the benchmarks) or
``solve(..., polish=True)`` gives certifiable output (docs/design/solver.md).
"""

from __future__ import annotations

import math
import time

import numpy as np

from mvreg.solver.base import IterationRecord, SolverContext, SolverRun
from mvreg.solver.blocks import feasible_x, project_blocks, rotations_from_x


def run(ctx: SolverContext) -> SolverRun:
    """Registry entry "gpm": GPM from ctx.start (see the module docstring)."""
    op, opts, R0 = ctx.operator, ctx.options, ctx.start
    d, n = op.d, op.n
    alpha = float(ctx.spectrum.largest)
    s2 = op.norm.scale**2
    scale = alpha * n  # f in [0, alpha n]
    # Start exactly on the constraint set (R0 may come from anywhere).
    X = feasible_x(R0, d, ctx.allow_reflections)
    CX = op.matvec(X)
    f = float(np.sum(X * CX))
    history = []
    converged = False
    increases = 0
    k = 0
    t0 = time.perf_counter()
    for k in range(1, opts.max_iter + 1):
        Y = alpha * X - CX
        X_new, attained = project_blocks(Y, d, ctx.allow_reflections)
        inner = float(np.sum(X * Y))
        fp_gap = 1.0 - inner / attained if attained > 0 else 0.0
        CX_new = op.matvec(X_new)
        f_new = float(np.sum(X_new * CX_new))
        dec = (f - f_new) / scale
        change = float(np.linalg.norm(X_new - X)) / math.sqrt(n)
        if f_new > f + 1e-12 * scale:
            increases += 1  # impossible in exact arithmetic (alpha I - C PSD): recorded
        X, CX, f = X_new, CX_new, f_new
        rec = IterationRecord(
            k,
            f * s2,
            primal_residual=0.0,
            dual_residual=change,
            extra={"relative_decrease": dec, "block_change": change, "fixed_point_gap": fp_gap},
        )
        ctx.emit(rec, history)
        if abs(dec) <= opts.tol and change <= opts.tol:
            converged = True
            break
    return SolverRun(
        rotations=np.ascontiguousarray(rotations_from_x(X, d)),
        iterations=k,
        converged=converged,
        history=history,
        stats={
            "alpha": alpha,
            "alpha_over_lambda_d_plus_1": alpha / float(ctx.spectrum.smallest[min(d, n - 1)])
            if ctx.spectrum.smallest[min(d, n - 1)] > 0
            else math.inf,
            "cost_increases": increases,
            "stopping_rule": "relative cost decrease and block change <= tol, or max_iter",
            "gpm_time_s": time.perf_counter() - t0,
        },
    )
