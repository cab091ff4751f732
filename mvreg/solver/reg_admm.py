"""REG-ADMM, paper 000 eq. (7), dense (reference) and matrix-free (DESIGN.md section 3).

    G <- top-d eigenpairs of A = H - (C + Lambda)/rho, negative eigenvalues clipped
    H <- G with every diagonal d x d block set to I
    Lambda <- Lambda + rho (G - H)            (block diagonal, Prop. 3)

The state is U (n, d), s (d) with G = U diag(s) U^T and the M dual blocks: memory is
linear in M. Since H = G - bd(G) + I, A = U diag(s) U^T + D - C/rho with the block
diagonal D = I - bd(G) - Lambda/rho. The dense variant forms A and uses an exact
eigensolver; the matrix-free one runs ``lobpcg_steps`` LOBPCG steps on the operator per
iteration, warm started from U.

rho = "auto": ``rho_policy`` "balanced" (lambda_max(C) / M, then residual balancing) or
"theorem4" (paper 000 Theorem 4's bound, doubled when the primal residual stalls): see
admm_rho.py. Every change is recorded with its reason (``SolverRun.rho_history``). A
number fixes rho. ``dual_start`` "multipliers" starts Lambda at -bd(C G) of the start.

Stopping: the relative primal residual ||bd(G) - I||_F / sqrt(Md) and the relative dual
residual ||H^{k+1} - H^k||_F / ||H^k||_F both below ``tol``, or ``max_iter``; or, with
``polish`` (the default), at a checkpoint (the start, then iterations 1, 2, 5, 10, 20, 50,
..., and max_iter) when the rounded iterate, Newton-polished to a KKT point, is certified
globally optimal. Without ``polish`` the run is plain eq. (7) (paper experiments).

Checkpoints (checkpoint.BestPoint): the rounded iterate is Newton-polished (further
passes when one stops short of a KKT point and the certificate fails) and certified; a
point rejected with negative curvature is escaped from by Riemannian-staircase steps
(staircase.py, ``staircase_rounds``) at checkpoint 0 and after the iterations.

Registry entry ``run(ctx)`` (see mvreg.solver.base): options ``solve.reg_admm``
(RegAdmmOptions: rho, rho_policy, dual_start, balance_window, stall_window,
staircase_rounds, max_iter, tol, polish, lobpcg_steps). Returns checked rotations: the best
polished point (lowest cost) over the checkpoints, the escapes and the last iterate, with
its certificate; or, without ``polish``, the rounded last iterate, certified.
Iteration records: objective Tr(C G) in the problem's units, the relative primal and dual
residuals, rho. Design notes: docs/design/solver.md.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from mvreg.solver.admm_rho import RhoPolicy, balanced_rho, theorem4_rho
from mvreg.solver.base import IterationRecord, SolverContext, SolverRun
from mvreg.solver.blocks import (
    block_apply,
    diag_blocks_of_cg,
    diag_blocks_of_gram,
    round_to_rotations,
    x_from_rotations,
)
from mvreg.solver.certificate import multipliers
from mvreg.solver.checkpoint import BestPoint

__all__ = ["AdmmState", "run", "run_reg_admm", "state_from_rotations", "theorem4_rho"]


@dataclass
class AdmmState:
    U: np.ndarray  # (n, d)
    s: np.ndarray  # (d,)
    lam: np.ndarray  # (M, d, d)
    rho: float


@dataclass
class AdmmRun:
    state: AdmmState
    history: list[IterationRecord] = field(default_factory=list)
    rho_changes: list[dict] = field(default_factory=list)
    iterations: int = 0
    residuals_converged: bool = False
    eig_steps: int = 0


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


def _g_update(op, U, s, lam, rho, c_dense, lobpcg_steps):
    """Top-d eigenpairs (w ascending, V) of A = U diag(s) U^T + D - C / rho, with the block
    diagonal D = I - bd(G) - Lambda / rho; also bd(G) of the current iterate."""
    d, m, n = op.d, op.M, op.n
    gd = diag_blocks_of_gram(U, s, d)
    dblk = np.eye(d) - gd - lam / rho
    if c_dense is not None:
        a = (U * s) @ U.T
        a -= c_dense / rho
        for i in range(m):
            a[i * d : (i + 1) * d, i * d : (i + 1) * d] += dblk[i]
        w, V = sla.eigh(a, subset_by_index=[n - d, n - 1], overwrite_a=True)
        return w, V, gd

    def apply(v):
        return U @ (s[:, None] * (U.T @ v)) + block_apply(dblk, v) - op.matvec(v) / rho

    aop = spla.LinearOperator((n, n), matvec=apply, matmat=apply, dtype=np.float64)
    with warnings.catch_warnings():  # a few warm-started steps per iteration by design
        warnings.simplefilter("ignore")
        w, V = spla.lobpcg(aop, U, largest=True, maxiter=lobpcg_steps, tol=1e-12 * m)
    order = np.argsort(w)
    return w[order], V[:, order], gd


def run_reg_admm(
    op,
    state: AdmmState,
    *,
    dense: bool,
    max_iter: int,
    tol: float,
    policy: RhoPolicy,
    checkpoint: Callable[[int, AdmmState], bool] | None = None,
    checkpoints: set[int] | None = None,
    callback: Callable[[IterationRecord], None] | None = None,
    lobpcg_steps: int = 4,
) -> AdmmRun:
    """Iterate eq. (7) from ``state``, rho from ``policy`` (admm_rho.RhoPolicy).
    ``checkpoint(k, state) -> True`` stops the loop."""
    d, m, n = op.d, op.M, op.n
    s2 = op.norm.scale**2
    run = AdmmRun(state=state)
    U, s, lam, rho = state.U, state.s, state.lam, policy.rho
    c_dense = op.dense() if dense else None
    for k in range(1, max_iter + 1):
        w, V, gd = _g_update(op, U, s, lam, rho, c_dense, lobpcg_steps)
        run.eig_steps += 1 if dense else lobpcg_steps
        s_new = np.maximum(w, 0.0)
        gd_new = diag_blocks_of_gram(V, s_new, d)
        resid_blocks = gd_new - np.eye(d)
        pr = float(np.linalg.norm(resid_blocks))
        # ||H1 - H0||^2 = ||G1 - G0||^2 - ||bd(G1) - bd(G0)||^2 (H = G off the diagonal).
        dh = math.sqrt(max(_gram_diff_sq(V, s_new, U, s) - float(np.sum((gd_new - gd) ** 2)), 0))
        h_norm = math.sqrt(max(float(np.sum(s**2)) - float(np.sum(gd**2)) + m * d, 1e-300))
        lam = lam + rho * resid_blocks
        U, s = V, s_new
        cu = op.matvec(U)
        obj = float(np.sum(s * np.sum(U * cu, axis=0))) * s2
        rec = IterationRecord(k, obj, pr / math.sqrt(n), dh / h_norm, rho)
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
        # The dual residual rho ||dH|| relative to the dual's scale ||bd(C G)|| (= ||Lambda*||
        # at a KKT point, Prop. 2).
        cg = float(np.linalg.norm(diag_blocks_of_cg(U, s, cu, d)))
        rho = policy.update(k, rec.primal_residual, rho * dh / max(cg, 1e-300))
    run.rho_changes = policy.changes
    return run


def rotations_from_state(state: AdmmState, d: int, allow_reflections: bool) -> np.ndarray:
    """O = diag(sqrt(s)) U^T, blocks rounded to SO(d) / O(d)."""
    return round_to_rotations(state.U * np.sqrt(np.maximum(state.s, 0.0)), d, allow_reflections)


def _rounded(state: AdmmState, ctx: SolverContext) -> np.ndarray:
    return rotations_from_state(state, ctx.operator.d, ctx.allow_reflections)


def _checkpoints(max_iter: int) -> set[int]:
    """Iterations after which the rounded iterate is polished and certified: 1, 2, 5, 10, ..."""
    pts, k = set(), 1
    while k <= max_iter:
        for b in (1, 2, 5):
            if b * k <= max_iter:
                pts.add(b * k)
        k *= 10
    pts.add(max_iter)
    return pts


def _policy(ctx: SolverContext) -> RhoPolicy:
    """The rho policy of the options (admm_rho): its kind, start and bounds."""
    op, o, spec = ctx.operator, ctx.options, ctx.spectrum
    d, m = op.d, op.M
    th4 = theorem4_rho(spec.lambda_d_plus_1(d), m, d)
    if o.rho != "auto":
        return RhoPolicy(float(o.rho), kind="fixed")
    if o.rho_policy == "theorem4":
        return RhoPolicy(th4, "theorem4", o.stall_window, rho_max=max(spec.largest, th4))
    rho0 = balanced_rho(spec.largest, m)
    # Capped at its start: above lambda_max(C) / M the steps only get shorter (admm_rho).
    return RhoPolicy(rho0, "balanced", o.balance_window, rho_min=th4, rho_max=rho0)


_RHO_REASONS = {
    "fixed": "fixed",
    "theorem4": "Theorem 4 bound",
    "balanced": "lambda_max(C) / M (power-step scale), then residual balancing",
}


def run(ctx: SolverContext) -> SolverRun:
    """Registry entry "reg-admm": REG-ADMM from ctx.start; with ``polish``, the rounded
    iterates are Newton-polished and certified at checkpoints (the start included) and the
    iterations stop once one is certified. Returns checked rotations (see base.SolverRun)."""
    op, o = ctx.operator, ctx.options
    policy = _policy(ctx)
    rho0 = policy.rho
    state = state_from_rotations(ctx.start, rho=rho0)
    best = BestPoint(ctx)
    t0 = time.perf_counter()
    # Checkpoint 0: the start itself. When the certificate rejects it with a direction of
    # negative curvature, staircase steps first; REG-ADMM iterates only when neither the
    # start nor an escape from it is certified (from the cheapest point found).
    # A lifted point's lower bound may show the uncertified start within LIFTED_GAP_STOP of
    # the optimum (a relaxation that is not tight): then there is nothing to iterate for.
    bounded = False
    if o.polish and (best.check(0, _rounded(state, ctx)) or best.escape(o.staircase_rounds)):
        admm = AdmmRun(state=state)
    elif o.polish and best.bounded:
        admm, bounded = AdmmRun(state=state), True
    else:
        if best.escapes:
            state = state_from_rotations(best.R, rho=rho0)
        if o.dual_start == "multipliers":
            X = x_from_rotations(best.R if best.escapes else ctx.start)
            state.lam = multipliers(X, op.matvec(X), op.d)[0]
        admm = run_reg_admm(
            op,
            state,
            dense=ctx.dense,
            max_iter=o.max_iter,
            tol=o.tol,
            policy=policy,
            checkpoint=(lambda k, st: best.check(k, _rounded(st, ctx))) if o.polish else None,
            checkpoints=_checkpoints(o.max_iter) if o.polish else None,
            callback=ctx.callback,
            lobpcg_steps=o.lobpcg_steps,
        )
    t_iter = time.perf_counter() - t0 - best.t_polish - best.t_cert - best.t_escape
    certified_early = best.certified
    if not certified_early and not bounded:
        best.finish(_rounded(admm.state, ctx), admm.iterations, o.polish)
        if o.polish:
            best.escape(o.staircase_rounds)
    best.apply_lifted_bound()
    pst = best.polish
    if pst is not None:
        pst.inverse = None  # free the factorization
    stopped = "residuals" if admm.residuals_converged else "max_iter"
    stopped = "lifted bound" if bounded else stopped
    return SolverRun(
        rotations=best.R,
        iterations=admm.iterations,
        converged=bool(best.certified or admm.residuals_converged),
        history=admm.history,
        stats={
            "residuals_converged": admm.residuals_converged,
            "stopped_by": "certificate" if certified_early else stopped,
            "staircase": best.escapes,
            "polished_at_iteration": best.at,
            "newton_steps": None if pst is None else pst.newton_steps,
            "newton_cg_steps": None if pst is None else pst.cg_steps,
            "eigensolver_steps": admm.eig_steps,
        },
        checked=True,
        certificate=best.cert,
        rho_initial=rho0,
        rho_final=policy.rho,
        rho_history=[{"iteration": 0, "rho": rho0, "reason": _RHO_REASONS[policy.kind]}]
        + admm.rho_changes,
        timings={
            "iterations": t_iter,
            "polish": best.t_polish,
            "certificate": best.t_cert,
            "staircase": best.t_escape,
        },
    )
