"""REG-ADMM, paper 000 eq. (7), dense (reference) and matrix-free (DESIGN.md section 3).

    G <- top-d eigenpairs of A = H - (C + Lambda)/rho, negative eigenvalues clipped
    H <- G with every diagonal d x d block set to I
    Lambda <- Lambda + rho (G - H)            (block diagonal, Prop. 3)

The state is U (n, d), s (d) with G = U diag(s) U^T and the M dual blocks: memory is
linear in M. Since H = G - bd(G) + I, A = U diag(s) U^T + D - C/rho with the block
diagonal D = I - bd(G) - Lambda/rho. The dense variant forms A and uses an exact
eigensolver; the matrix-free one runs LOBPCG on the operator, warm started from U.

rho = "auto": Theorem 4's value lambda_{d+1}(C) / (2 M sqrt(d)) (feasible H0, Lambda0 = 0),
doubled whenever the primal residual stops decreasing (the non-attenuating oscillation of
paper section 2.6), up to lambda_max(C). Every change is recorded with its reason.

Stopping: the relative primal residual ||bd(G) - I||_F / sqrt(Md) and the relative dual
residual ||H^{k+1} - H^k||_F / ||H^k||_F both below ``tol``; or, at checkpoints, when the
rounded iterate, Newton-polished to a KKT point, is certified globally optimal.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from mvreg.solver.blocks import (
    block_apply,
    diag_blocks_of_gram,
    round_to_rotations,
    x_from_rotations,
)


@dataclass
class AdmmState:
    U: np.ndarray  # (n, d)
    s: np.ndarray  # (d,)
    lam: np.ndarray  # (M, d, d)
    rho: float


@dataclass
class IterationRecord:
    iteration: int
    objective: float  # Tr(C G) in the problem's units
    primal_residual: float
    dual_residual: float
    rho: float


@dataclass
class AdmmRun:
    state: AdmmState
    history: list[IterationRecord] = field(default_factory=list)
    rho_changes: list[dict] = field(default_factory=list)
    iterations: int = 0
    residuals_converged: bool = False
    eig_steps: int = 0


def theorem4_rho(lam_d1: float, m: int, d: int, h0_norm: float | None = None) -> float:
    """Theorem 4: rho <= lambda_{d+1}(C) / sqrt(||H0||^2 + 2 M sqrt(d) ||H0|| + M^2 d)."""
    h = m * math.sqrt(d) if h0_norm is None else h0_norm
    return lam_d1 / math.sqrt(h * h + 2 * m * math.sqrt(d) * h + m * m * d)


def _gram_diff_sq(U1, s1, U0, s0) -> float:
    """||U1 S1 U1^T - U0 S0 U0^T||_F^2 in O(n d^2)."""
    g = U1.T @ U0
    return float(np.sum(s1**2) + np.sum(s0**2) - 2.0 * np.sum(np.outer(s1, s0) * g * g))


def state_from_rotations(R: np.ndarray, lam: np.ndarray | None = None, rho: float = 1.0):
    """Feasible G = O^T O from rotations, as U (n, d), s = M (Prop. 1)."""
    m, d, _ = R.shape
    X = x_from_rotations(R)
    U = X / math.sqrt(m)
    if lam is None:
        lam = np.zeros((m, d, d))
    return AdmmState(U=U, s=np.full(d, float(m)), lam=lam, rho=rho)


def run_reg_admm(
    op,
    state: AdmmState,
    *,
    dense: bool,
    max_iter: int,
    tol: float,
    rho_mode: str,
    rho_max: float,
    checkpoint: Callable[[int, AdmmState], bool] | None = None,
    checkpoints: set[int] | None = None,
    callback: Callable[[IterationRecord], None] | None = None,
    lobpcg_steps: int = 4,
    stall_window: int = 10,
) -> AdmmRun:
    """Iterate eq. (7) from ``state``. ``checkpoint(k, state) -> True`` stops the loop."""
    d, m, n = op.d, op.M, op.n
    eye = np.eye(d)
    s2 = op.norm.scale**2
    run = AdmmRun(state=state)
    U, s, lam, rho = state.U, state.s, state.lam, state.rho
    best_pr, best_at = np.inf, 0
    c_dense = op.dense() if dense else None
    for k in range(1, max_iter + 1):
        gd = diag_blocks_of_gram(U, s, d)
        dblk = eye - gd - lam / rho
        if dense:
            a = (U * s) @ U.T
            a -= c_dense / rho
            for i in range(m):
                a[i * d : (i + 1) * d, i * d : (i + 1) * d] += dblk[i]
            w, V = sla.eigh(a, subset_by_index=[n - d, n - 1], overwrite_a=True)
            run.eig_steps += 1
        else:

            def apply(v, U=U, s=s, dblk=dblk, rho=rho):
                return U @ (s[:, None] * (U.T @ v)) + block_apply(dblk, v) - op.matvec(v) / rho

            aop = spla.LinearOperator((n, n), matvec=apply, matmat=apply, dtype=np.float64)
            with warnings.catch_warnings():  # a few warm-started steps per iteration by design
                warnings.simplefilter("ignore")
                w, V = spla.lobpcg(aop, U, largest=True, maxiter=lobpcg_steps, tol=1e-12 * m)
            run.eig_steps += lobpcg_steps
            order = np.argsort(w)
            w, V = w[order], V[:, order]
        s_new = np.maximum(w, 0.0)
        gd_new = diag_blocks_of_gram(V, s_new, d)
        resid_blocks = gd_new - eye
        pr = float(np.linalg.norm(resid_blocks))
        # ||H1 - H0||^2 = ||G1 - G0||^2 - ||bd(G1) - bd(G0)||^2 (H = G off the diagonal).
        dh2 = _gram_diff_sq(V, s_new, U, s) - float(np.sum((gd_new - gd) ** 2))
        h_norm = math.sqrt(max(float(np.sum(s**2)) - float(np.sum(gd**2)) + m * d, 1e-300))
        dr = math.sqrt(max(dh2, 0.0)) / h_norm
        lam = lam + rho * resid_blocks
        U, s = V, s_new
        cu = op.matvec(U)
        obj = float(np.sum(s * np.sum(U * cu, axis=0))) * s2
        rec = IterationRecord(k, obj, pr / math.sqrt(n), dr, rho)
        run.history.append(rec)
        run.iterations = k
        if callback is not None:
            callback(rec)
        state = AdmmState(U, s, lam, rho)
        run.state = state
        if rec.primal_residual <= tol and rec.dual_residual <= tol:
            run.residuals_converged = True
            break
        if checkpoint is not None and checkpoints is not None and k in checkpoints:
            if checkpoint(k, state):
                break
        # rho policy: raise rho when the primal residual stops decreasing.
        if rec.primal_residual < 0.99 * best_pr:
            best_pr, best_at = rec.primal_residual, k
        elif rho_mode == "auto" and k - best_at >= stall_window and rho < rho_max:
            new = min(2.0 * rho, rho_max)
            run.rho_changes.append(
                {
                    "iteration": k,
                    "rho": new,
                    "previous": rho,
                    "reason": f"primal residual stalled at {rec.primal_residual:.3g} "
                    f"for {stall_window} iterations (oscillation, paper 000 sec. 2.6)",
                }
            )
            rho = new
            best_pr, best_at = rec.primal_residual, k
    return run


def rotations_from_state(state: AdmmState, d: int, allow_reflections: bool) -> np.ndarray:
    """O = diag(sqrt(s)) U^T, blocks rounded to SO(d) / O(d)."""
    return round_to_rotations(state.U * np.sqrt(np.maximum(state.s, 0.0)), d, allow_reflections)
