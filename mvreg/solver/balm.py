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
lambda_max(C) (multiplier updates only from there on). Without them mu grew without bound
once X = Q to machine precision and the Q-updates (steps ~1/mu) stalled.

Paper 002 Theorem 2: with bounded multipliers every limit point satisfies the first-order
conditions, i.e. Q is a KKT point of O-REG (paper 000 Lemma 1).

Defaults: mu_0 = lambda_{d+1}(C) (the scale of C on the complement of the solution),
gamma = 2, eta = 0.25, Y_0 = -2 C Q_0 (the multiplier consistent with X = Q = Q_0).

Stopping rule: after an outer iteration, stop when both the relative consensus residual
||X - Q||_F / sqrt(n) and the KKT residual of Q, ||(C + Lambda) Q||_F / (lambda_max sqrt(n))
(the certificate's definition), are <= ctx.tol; or after ctx.max_iter outer iterations.
The output is Q (always feasible).

Accuracy: the certificate (solve()) bounds the suboptimality by ~||grad||^2 / mu, so on
noisy data a KKT residual of ~1e-6 (what tol = 1e-6 gives) is often too inexact to be
certified although the point is the global optimum; tol ~1e-9 (used in the benchmarks) or
``solve(..., polish_steps=True)`` gives certifiable output.
"""

from __future__ import annotations

import math
import time

import numpy as np
import scipy.linalg as sla

from mvreg.solver.blocks import block_apply, round_to_rotations, x_from_rotations
from mvreg.solver.certificate import multipliers
from mvreg.solver.gpm import _project_blocks


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


def run_balm(
    op,
    R0: np.ndarray,
    ctx,
    *,
    mu0: float | None = None,
    gamma: float = 2.0,
    eta: float = 0.25,
    inner_max: int = 50,
    inner_tol: float | None = None,
    mu_max_factor: float = 10.0,
    inner_rel: float = 0.1,
    cg_rtol: float = 1e-10,
    cg_maxiter: int = 500,
):
    """BALM from rotations R0 (M, d, d); returns a GenericRun (see module docstring)."""
    from mvreg.solver.solvers import GenericRun

    d, n = op.d, op.n
    lam_max = float(ctx.spectrum.largest)
    lam_d1 = float(ctx.spectrum.smallest[min(d, n - 1)])
    s2 = op.norm.scale**2
    mu = float(mu0) if mu0 is not None else max(lam_d1, 1e-6 * lam_max)
    mu_max = mu_max_factor * lam_max
    adaptive_inner = inner_tol is None
    inner_tol = ctx.tol if inner_tol is None else inner_tol
    xs = _XSolver(op, ctx.dense, cg_rtol, cg_maxiter)
    Q = x_from_rotations(round_to_rotations(x_from_rotations(R0), d, ctx.allow_reflections))
    X = Q.copy()
    Y = -2.0 * op.matvec(Q)
    eps_best = math.inf
    history = []
    converged = False
    sweeps = 0
    mult_updates = 0
    mu_increases = 0
    k = 0
    t0 = time.perf_counter()
    sub = 1.0
    kkt = math.inf
    for k in range(1, ctx.max_iter + 1):
        xs.set_mu(mu)
        if adaptive_inner:
            # Inexact inner solves: a tenth of the last KKT residual (never below tol).
            inner_tol = max(ctx.tol, inner_rel * kkt) if math.isfinite(kkt) else 1e-2
        # Gauss-Seidel sweeps on L_mu(., .; Y) (Algorithm 2.1). After a sweep the X-part of
        # the subproblem gradient is mu (Q_old - Q_new) (the X-update is exact), so the
        # subproblem is solved to first order when mu ||dQ|| is small.
        for _ in range(inner_max):
            # Inexact X-solves (matrix-free): the residual of (2C + mu I) X = mu Q - Y is an
            # error in the X-gradient of L_mu; keep it a tenth of the current subproblem
            # residual (and of inner_tol at the end), in the same units.
            atol = 0.1 * max(inner_tol, sub) * lam_max * math.sqrt(n)
            X = xs.solve(mu * Q - Y, X, atol)
            Q_new, _ = _project_blocks(X + Y / mu, d, ctx.allow_reflections)
            sweeps += 1
            sub = mu * float(np.linalg.norm(Q_new - Q)) / (lam_max * math.sqrt(n))
            Q = Q_new
            if sub <= inner_tol:
                break
        diff = X - Q
        eps = float(np.sum(diff * diff))
        CQ = op.matvec(Q)
        _, grad = multipliers(Q, CQ, d)
        kkt = float(np.linalg.norm(grad)) / (lam_max * math.sqrt(n))
        primal = math.sqrt(eps / n)
        # Algorithm 3.1, with two safeguards: a consensus residual already below tol counts as
        # sufficient decrease, and mu stops growing at mu_max (beyond ~lambda_max a larger
        # penalty only slows the Q-updates down).
        if eps < eta * eps_best or primal <= ctx.tol or mu >= mu_max:
            Y = Y + mu * diff
            eps_best = min(eps, eps_best)
            mult_updates += 1
            action = "multiplier"
        else:
            mu = min(gamma * mu, mu_max)
            mu_increases += 1
            action = "penalty"
        rec = {
            "iteration": k,
            "objective": float(np.sum(Q * CQ)) * s2,
            "primal_residual": primal,
            "kkt_residual": kkt,
            "mu": mu,
            "update": action,
            "sweeps": sweeps,
        }
        history.append(rec)
        if ctx.callback is not None:
            ctx.callback(rec)
        if primal <= ctx.tol and kkt <= ctx.tol:
            converged = True
            break
    R = Q.reshape(-1, d, d).transpose(0, 2, 1)
    return GenericRun(
        rotations=np.ascontiguousarray(R),
        iterations=k,
        converged=converged,
        history=history,
        stats={
            "gauss_seidel_sweeps": sweeps,
            "multiplier_updates": mult_updates,
            "penalty_increases": mu_increases,
            "mu_initial": float(mu0) if mu0 is not None else max(lam_d1, 1e-6 * lam_max),
            "mu_final": mu,
            "kkt_residual_final": history[-1]["kkt_residual"] if history else math.nan,
            "x_solver": "cholesky" if ctx.dense else "block-cg",
            "cholesky_factorizations": xs.factorizations,
            "cg_steps": xs.cg_steps,
            "balm_time_s": time.perf_counter() - t0,
        },
    )
