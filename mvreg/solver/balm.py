"""BALM-style augmented Lagrangian method (paper 002 Sec. 3, Algorithms 2.1 and 3.1).

Problem: min f(X) = Tr(X^T C X) over X = O^T (n x d) whose d x d blocks lie in SO(d) (or
O(d)). Split X = Q with Q on the manifold (paper 002 eq. 21, x2 = X, x3 = Q) and dualize
only the consensus constraint:

    L_mu(X, Q; Y) = Tr(X^T C X) + <Y, X - Q> + mu/2 ||X - Q||_F^2.

Outer iteration k (Algorithm 3.1) approximately minimizes L_mu over (X, Q) by Gauss-Seidel
sweeps (Algorithm 2.1), each one

    X-update:  (2C + mu I) X = mu Q - Y     (dense: one Cholesky factor per value of mu;
                                             matrix-free: block CG through op.matvec,
                                             warm-started, block-Jacobi preconditioned,
                                             inexact: residual <= 0.1 x the current
                                             subproblem residual)
    Q-update:  Q_i = proj_{SO(d)/O(d)}(X_i + Y_i / mu)    (blockwise SVD)

until the subproblem is solved to first order: after a sweep the X-gradient of L_mu is
mu (Q_old - Q_new) (the X-update is exact), so the sweeps stop when
mu ||Q_new - Q_old||_F / (lambda_max sqrt(n)) <= inner_tol, with inner_tol = max(tol,
0.1 x the previous outer KKT residual) (1e-2 at the first outer iteration), or after
``inner_max`` (50) sweeps. Then, with eps = ||X - Q||_F^2:

    if eps < eta * eps_best:  Y <- Y + mu (X - Q), eps_best <- eps     (multiplier update)
    else:                     mu <- gamma * mu                          (increase penalty)

with two safeguards added to Algorithm 3.1: a consensus residual already below tol counts
as sufficient decrease (no penalty increase), and mu stops growing at mu_max = 10
lambda_max(C) (multiplier updates only from there on); why: docs/design/solver.md.

Paper 002 Theorem 2: with bounded multipliers every limit point satisfies the first-order
conditions, i.e. Q is a KKT point of O-REG (paper 000 Lemma 1).

Defaults: mu_0 = lambda_{d+1}(C) (the scale of C on the complement of the solution),
gamma = 2, eta = 0.25, Y_0 = -2 C Q_0 (the multiplier consistent with X = Q = Q_0).

Stopping rule: after an outer iteration, stop when both the relative consensus residual
||X - Q||_F / sqrt(n) and the KKT residual of Q, ||(C + Lambda) Q||_F / (lambda_max sqrt(n))
(the certificate's definition), are <= tol; or after max_iter outer iterations.
The output is Q (always feasible).

Options: ``solve.balm`` (BalmOptions: max_iter, tol, polish, mu0, gamma, eta, inner_max,
inner_tol, mu_max_factor, inner_rel, cg_rtol, cg_maxiter). Iteration records: the
objective f(Q) in the problem's units; primal_residual the consensus residual;
dual_residual the KKT residual of Q; rho the penalty mu; extra: kkt_residual, mu, update
("multiplier" or "penalty"), sweeps (cumulative).

Accuracy: the certificate (solve()) bounds the suboptimality by ~||grad||^2 / mu, so on
noisy data a KKT residual of ~1e-6 (what tol = 1e-6 gives) is often too inexact to be
certified although the point is the global optimum; tol ~1e-9 (used in the benchmarks) or
``solve(..., polish=True)`` gives certifiable output (docs/design/solver.md).
"""

from __future__ import annotations

import math
import time

import numpy as np
import scipy.linalg as sla

from mvreg.solver.base import IterationRecord, SolverContext, SolverRun
from mvreg.solver.blocks import block_apply, feasible_x, project_blocks, rotations_from_x
from mvreg.solver.certificate import multipliers


class _XSolver:
    """Solves (2C + mu I) X = B for (n, d) right-hand sides."""

    def __init__(self, op, dense: bool, cg_rtol: float, cg_maxiter: int):
        self.op = op
        self.dense = dense
        self.mu = None
        self.cg_rtol = cg_rtol
        self.cg_maxiter = cg_maxiter
        self.cg_steps = 0
        self.factorizations = 0
        d = op.d
        if not dense:
            # Block-Jacobi preconditioner from the diagonal blocks of C0 (an upper bound on
            # those of C = C0 - B S^+ B^T; cheap and SPD).
            c0 = op.C0
            idx = np.arange(op.n)
            blk = idx // d
            coo = c0.tocoo()
            keep = blk[coo.row] == blk[coo.col]
            self._c0_blocks = np.zeros((op.M, d, d))
            np.add.at(
                self._c0_blocks,
                (blk[coo.row[keep]], coo.row[keep] % d, coo.col[keep] % d),
                coo.data[keep],
            )

    def set_mu(self, mu: float) -> None:
        if mu == self.mu:
            return
        self.mu = mu
        d = self.op.d
        if self.dense:
            a = 2.0 * self.op.dense()
            a = a + mu * np.eye(self.op.n)
            self._cho = sla.cho_factor(a, lower=True, check_finite=False)
            self.factorizations += 1
        else:
            self._prec = np.linalg.inv(2.0 * self._c0_blocks + mu * np.eye(d)[None])

    def apply(self, V: np.ndarray) -> np.ndarray:
        return 2.0 * self.op.matvec(V) + self.mu * V

    def solve(self, B: np.ndarray, X0: np.ndarray, atol: float = 0.0) -> np.ndarray:
        """X with (2C + mu I) X ~ B: exact (dense) or by CG until every column's residual is
        below max(cg_rtol ||b||, atol / sqrt(d))."""
        if self.dense:
            return sla.cho_solve(self._cho, B, check_finite=False)
        # Block (column-wise) preconditioned CG, all d columns at once.
        X = X0.copy()
        R = B - self.apply(X)
        bnorm = np.maximum(self.cg_rtol * np.linalg.norm(B, axis=0), atol / math.sqrt(B.shape[1]))
        Z = block_apply(self._prec, R)
        P = Z.copy()
        rz = np.sum(R * Z, axis=0)
        for _ in range(self.cg_maxiter):
            if np.all(np.linalg.norm(R, axis=0) <= bnorm):
                break
            AP = self.apply(P)
            self.cg_steps += 1
            pap = np.sum(P * AP, axis=0)
            a = np.where(pap > 0, rz / np.where(pap > 0, pap, 1.0), 0.0)
            X += P * a
            R -= AP * a
            Z = block_apply(self._prec, R)
            rz_new = np.sum(R * Z, axis=0)
            beta = np.where(rz > 0, rz_new / np.where(rz > 0, rz, 1.0), 0.0)
            P = Z + P * beta
            rz = rz_new
        return X


def _sweeps(xs, X, Q, Y, mu, inner_tol, sub, lam_max, ctx):
    """Gauss-Seidel sweeps on L_mu(., .; Y) (Algorithm 2.1) until the subproblem is solved
    to first order. Returns (X, Q, subproblem residual, sweeps done)."""
    d, n = ctx.operator.d, ctx.operator.n
    done = 0
    # After a sweep the X-part of the subproblem gradient is mu (Q_old - Q_new) (the
    # X-update is exact), so the subproblem is solved to first order when mu ||dQ|| is small.
    for _ in range(ctx.options.inner_max):
        # Inexact X-solves (matrix-free): the residual of (2C + mu I) X = mu Q - Y is an
        # error in the X-gradient of L_mu; keep it a tenth of the current subproblem
        # residual (and of inner_tol at the end), in the same units.
        atol = 0.1 * max(inner_tol, sub) * lam_max * math.sqrt(n)
        X = xs.solve(mu * Q - Y, X, atol)
        Q_new, _ = project_blocks(X + Y / mu, d, ctx.allow_reflections)
        done += 1
        sub = mu * float(np.linalg.norm(Q_new - Q)) / (lam_max * math.sqrt(n))
        Q = Q_new
        if sub <= inner_tol:
            break
    return X, Q, sub, done


def run(ctx: SolverContext) -> SolverRun:
    """Registry entry "balm": BALM from ctx.start (see the module docstring)."""
    op, o = ctx.operator, ctx.options
    d, n = op.d, op.n
    lam_max = float(ctx.spectrum.largest)
    lam_d1 = float(ctx.spectrum.smallest[min(d, n - 1)])
    s2 = op.norm.scale**2
    mu = mu_initial = float(o.mu0) if o.mu0 is not None else max(lam_d1, 1e-6 * lam_max)
    mu_max = o.mu_max_factor * lam_max
    inner_tol = o.tol if o.inner_tol is None else o.inner_tol
    xs = _XSolver(op, ctx.dense, o.cg_rtol, o.cg_maxiter)
    Q = feasible_x(ctx.start, d, ctx.allow_reflections)
    X = Q.copy()
    Y = -2.0 * op.matvec(Q)
    eps_best = math.inf
    history = []
    converged = False
    sweeps = 0
    counts = {"multiplier_updates": 0, "penalty_increases": 0}
    k = 0
    t0 = time.perf_counter()
    sub = 1.0
    kkt = math.inf
    for k in range(1, o.max_iter + 1):
        xs.set_mu(mu)
        if o.inner_tol is None:
            # Inexact inner solves: a tenth of the last KKT residual (never below tol).
            inner_tol = max(o.tol, o.inner_rel * kkt) if math.isfinite(kkt) else 1e-2
        X, Q, sub, done = _sweeps(xs, X, Q, Y, mu, inner_tol, sub, lam_max, ctx)
        sweeps += done
        diff = X - Q
        eps = float(np.sum(diff * diff))
        CQ = op.matvec(Q)
        _, grad = multipliers(Q, CQ, d)
        kkt = float(np.linalg.norm(grad)) / (lam_max * math.sqrt(n))
        primal = math.sqrt(eps / n)
        # Algorithm 3.1, with two safeguards: a consensus residual already below tol counts as
        # sufficient decrease, and mu stops growing at mu_max (beyond ~lambda_max a larger
        # penalty only slows the Q-updates down).
        if eps < o.eta * eps_best or primal <= o.tol or mu >= mu_max:
            Y = Y + mu * diff
            eps_best = min(eps, eps_best)
            counts["multiplier_updates"] += 1
            action = "multiplier"
        else:
            mu = min(o.gamma * mu, mu_max)
            counts["penalty_increases"] += 1
            action = "penalty"
        rec = IterationRecord(
            k,
            float(np.sum(Q * CQ)) * s2,
            primal_residual=primal,
            dual_residual=kkt,
            rho=mu,
            extra={"kkt_residual": kkt, "mu": mu, "update": action, "sweeps": sweeps},
        )
        ctx.emit(rec, history)
        if primal <= o.tol and kkt <= o.tol:
            converged = True
            break
    return SolverRun(
        rotations=np.ascontiguousarray(rotations_from_x(Q, d)),
        iterations=k,
        converged=converged,
        history=history,
        stats={
            "gauss_seidel_sweeps": sweeps,
            **counts,
            "mu_initial": mu_initial,
            "mu_final": mu,
            "kkt_residual_final": history[-1].dual_residual if history else math.nan,
            "x_solver": "cholesky" if ctx.dense else "block-cg",
            "cholesky_factorizations": xs.factorizations,
            "cg_steps": xs.cg_steps,
            "balm_time_s": time.perf_counter() - t0,
        },
    )
