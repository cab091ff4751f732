"""solve(): the one entry point of the global stage.

build C -> spectrum (lambda_{d+1}, lambda_max, spectral init) -> solver iterations
-> (Newton polish + certificate at checkpoints) -> closed-form translations -> gauge.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from mvreg.errors import ConfigError, IllPosedError
from mvreg.solver.certificate import DEFAULT_GAP_TOL, certify
from mvreg.solver.operator import RegOperator
from mvreg.solver.polish import polish
from mvreg.solver.problem import PatchProblem
from mvreg.solver.reg_admm import (
    AdmmRun,
    IterationRecord,
    rotations_from_state,
    run_reg_admm,
    state_from_rotations,
    theorem4_rho,
)
from mvreg.solver.result import SolveResult
from mvreg.solver.solvers import GENERIC_SOLVERS, SolverContext
from mvreg.solver.spectral import spectral_rotations, spectrum

SOLVERS = ("reg-admm", *GENERIC_SOLVERS)
# Dense (exact eigendecomposition per iteration) up to this M d; matrix-free above.
DENSE_MAX_N = 900
# lambda_{d+1}(C) / lambda_max(C) below this: some rotation is not determined.
ILL_POSED_RATIO = 1e-10


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


# Multi-threaded OpenBLAS made dense eigensolvers ~10-30x slower on the 2-core machine
# this was measured on; solve() runs with one BLAS thread (recorded in the result).
BLAS_THREADS = 1


def solve(problem: PatchProblem, *args, **kwargs) -> SolveResult:
    """Solve REG for a patch problem (see ``_solve`` for the arguments)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=BLAS_THREADS, user_api="blas"):
        res = _solve(problem, *args, **kwargs)
    res.stats["blas_threads"] = BLAS_THREADS
    return res


def _solve(
    problem: PatchProblem,
    solver: str = "reg-admm",
    *,
    method: str = "auto",
    rho: str | float = "auto",
    max_iter: int = 500,
    tol: float = 1e-6,
    gap_tol: float = DEFAULT_GAP_TOL,
    allow_reflections: bool = False,
    init: np.ndarray | str = "spectral",
    polish_steps: bool | None = None,
    certify_result: bool = True,
    gauge: str = "first",
    seed: int = 0,
    callback: Callable[[IterationRecord], None] | None = None,
    operator: RegOperator | None = None,
) -> SolveResult:
    """Solve REG for a patch problem: rotations, translations, nodes, certificate.

    Args:
        problem: the PatchProblem.
        solver: "reg-admm" (default).
        method: "dense" (exact eigendecompositions, small problems), "matrix-free"
            (LOBPCG on an operator, memory linear in M) or "auto" (dense up to M d = 900).
        rho: "auto" (Theorem 4, raised on oscillation) or a positive number.
        max_iter: cap on REG-ADMM iterations.
        tol: relative primal and dual residual tolerance of REG-ADMM.
        gap_tol: certified when the relative suboptimality bound is below this.
        allow_reflections: O(d) instead of SO(d).
        init: "spectral" or rotations (M, d, d) R_world_patch to start from.
        polish_steps: Newton-polish rounded iterates at checkpoints (stop when certified);
            False runs plain eq. (7) to its residual tolerance (paper experiments).
            Default: True for reg-admm, False for the other solvers (their own output is
            certified as it is).
        certify_result: compute the certificate (True in every user-facing path).
        gauge: "first" (patch 0 = world frame) or "none".
        seed: seeds the random starts of the iterative eigensolvers.
        callback: called with each IterationRecord.
        operator: a prebuilt RegOperator for this problem (warm restarts).
    """
    if solver not in SOLVERS:
        raise ConfigError(f"unknown solver '{solver}' (choose from {', '.join(SOLVERS)})")
    if method not in ("auto", "dense", "matrix-free"):
        raise ConfigError(f"unknown method '{method}' (auto, dense or matrix-free)")
    if max_iter < 1:
        raise ConfigError(f"max_iter must be >= 1, got {max_iter}")
    if not (0 < tol < 1):
        raise ConfigError(f"tol must be in (0, 1), got {tol}")
    if isinstance(rho, str) and rho != "auto":
        raise ConfigError(f"rho must be 'auto' or a positive number, got '{rho}'")
    if not isinstance(rho, str) and not (rho > 0 and math.isfinite(rho)):
        raise ConfigError(f"rho must be 'auto' or a positive number, got {rho}")
    t_start = time.perf_counter()
    timings = {}
    op = operator if operator is not None else RegOperator(problem)
    d, m = op.d, op.M
    dense = method == "dense" or (method == "auto" and op.n <= DENSE_MAX_N)
    timings["build_C"] = time.perf_counter() - t_start

    t0 = time.perf_counter()
    spec = spectrum(op, dense=dense, seed=seed)
    lam_max = spec.largest
    lam_d1 = float(spec.smallest[d]) if m > 1 else lam_max
    if m > 1 and lam_d1 <= ILL_POSED_RATIO * lam_max:
        bad = [problem.patch_names[i] for i in problem.underdetermined_patches()]
        raise IllPosedError(
            f"ill-posed: lambda_{d + 1}(C) = {lam_d1:.3g} ~ 0 (lambda_max {lam_max:.3g}): some "
            "rotation is not determined by the data"
            + (f" (patches {', '.join(bad[:10])})" if bad else ""),
            bad,
        )
    if isinstance(init, str):
        if init != "spectral":
            raise ConfigError(f"unknown init '{init}' (spectral, or rotations)")
        R0 = spectral_rotations(spec, d, allow_reflections)
    else:
        R0 = np.asarray(init, dtype=np.float64)
        if R0.shape != (m, d, d) or not np.all(np.isfinite(R0)):
            raise ConfigError(f"init rotations must have shape {(m, d, d)} and be finite")

    timings["init"] = time.perf_counter() - t0

    if solver != "reg-admm":
        return _solve_generic(
            problem,
            op,
            solver,
            R0,
            spec,
            dense,
            timings,
            t_start,
            SolverContext(dense, max_iter, tol, allow_reflections, spec, seed, callback, rho),
            polish_steps=polish_steps if polish_steps is not None else False,
            certify_result=certify_result,
            gap_tol=gap_tol,
            gauge=gauge,
        )
    polish_steps = True if polish_steps is None else polish_steps
    rho0 = theorem4_rho(lam_d1, m, d) if rho == "auto" else float(rho)
    state = state_from_rotations(R0, rho=rho0)
    best = {"R": None, "f": np.inf, "cert": None, "polish": None, "at": None}
    t_polish = [0.0]
    t_cert = [0.0]

    def check(k, st) -> bool:
        R = rotations_from_state(st, d, allow_reflections)
        t1 = time.perf_counter()
        Rp, pst = polish(op, R, lam_max, allow_reflections)
        t_polish[0] += time.perf_counter() - t1
        if pst.objective >= best["f"] - 1e-12 * max(abs(best["f"]), 1e-300):
            return False  # same stationary point as before: already checked
        t2 = time.perf_counter()
        cert = (
            certify(op, Rp, lam_max, dense, gap_tol, seed, inverse=pst.inverse)
            if certify_result
            else None
        )
        pst.inverse = None  # free the factorization
        t_cert[0] += time.perf_counter() - t2
        best.update(R=Rp, f=pst.objective, cert=cert, polish=pst, at=k)
        return bool(cert is not None and cert.certified)

    # Checkpoint 0: the start itself. In the low-noise regime the spectral estimate lies in
    # the basin of the global optimum and is certified after a few Newton steps; REG-ADMM
    # iterates only when it is not.
    t0 = time.perf_counter()
    if polish_steps and check(0, state):
        run = AdmmRun(state=state)
    else:
        run = run_reg_admm(
            op,
            state,
            dense=dense,
            max_iter=max_iter,
            tol=tol,
            rho_mode="auto" if rho == "auto" else "fixed",
            rho_max=max(lam_max, rho0),
            checkpoint=check if polish_steps else None,
            checkpoints=_checkpoints(max_iter) if polish_steps else None,
            callback=callback,
        )
    timings["iterations"] = time.perf_counter() - t0 - t_polish[0] - t_cert[0]
    certified_early = best["cert"] is not None and best["cert"].certified
    if not certified_early:
        R_final = rotations_from_state(run.state, d, allow_reflections)
        if polish_steps:
            t1 = time.perf_counter()
            Rp, pst = polish(op, R_final, lam_max, allow_reflections)
            t_polish[0] += time.perf_counter() - t1
            if pst.objective < best["f"]:
                best.update(R=Rp, f=pst.objective, polish=pst, at=run.iterations, cert=None)
        elif best["R"] is None:
            best.update(R=R_final, at=run.iterations)
        if best["R"] is R_final or best["cert"] is None:
            t2 = time.perf_counter()
            inv = best["polish"].inverse if best["polish"] is not None else None
            best["cert"] = (
                certify(op, best["R"], lam_max, dense, gap_tol, seed, inverse=inv)
                if certify_result
                else None
            )
            t_cert[0] += time.perf_counter() - t2
    if best["polish"] is not None:
        best["polish"].inverse = None  # free the factorization
    timings["polish"] = t_polish[0]
    timings["certificate"] = t_cert[0]

    R, t, z = _finish(op, best["R"], gauge, timings, t_start)
    cert = best["cert"]
    objective = op.residual(R, t, z)
    pst = best["polish"]
    return SolveResult(
        rotations=R,
        translations=t,
        nodes=z,
        patch_names=list(problem.patch_names),
        objective=objective,
        iterations=run.iterations,
        converged=bool((cert is not None and cert.certified) or run.residuals_converged),
        certificate=cert,
        solver=solver,
        method="dense" if dense else "matrix-free",
        rho_initial=rho0,
        rho_final=run.state.rho if not run.rho_changes else run.rho_changes[-1]["rho"],
        rho_history=[
            {"iteration": 0, "rho": rho0, "reason": "Theorem 4 bound" if rho == "auto" else "fixed"}
        ]
        + run.rho_changes,
        history=[r.__dict__ for r in run.history],
        timings=timings,
        stats={
            "lambda_d_plus_1": lam_d1,
            "lambda_max": lam_max,
            "spectral_gap_ratio": lam_d1 / lam_max,
            "residuals_converged": run.residuals_converged,
            "stopped_by": "certificate"
            if certified_early
            else ("residuals" if run.residuals_converged else "max_iter"),
            "polished_at_iteration": best["at"],
            "newton_steps": None if pst is None else pst.newton_steps,
            "newton_cg_steps": None if pst is None else pst.cg_steps,
            "eigensolver_steps": run.eig_steps,
            "C_products": op.num_matvecs,
            "laplacian": op.lap.method,
        },
    )


def _finish(op, R, gauge, timings, t_start):
    """Closed-form translations and nodes for R, then the gauge (patch 0 = world)."""
    t0 = time.perf_counter()
    t, z = op.translations(R)
    if gauge == "first":
        r0, t0v = R[0].copy(), t[0].copy()
        R = np.einsum("ba,mbc->mac", r0, R)
        t = (t - t0v) @ r0
        z = (z - t0v) @ r0
    timings["translations"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    return R, t, z


def _solve_generic(
    problem,
    op,
    solver,
    R0,
    spec,
    dense,
    timings,
    t_start,
    ctx,
    *,
    polish_steps,
    certify_result,
    gap_tol,
    gauge,
) -> SolveResult:
    t0 = time.perf_counter()
    run = GENERIC_SOLVERS[solver](op, R0, ctx)
    timings["iterations"] = time.perf_counter() - t0
    R = run.rotations
    stats = dict(run.stats)
    if polish_steps:
        t0 = time.perf_counter()
        R, pst = polish(op, R, spec.largest, ctx.allow_reflections)
        timings["polish"] = time.perf_counter() - t0
        stats.update(newton_steps=pst.newton_steps, newton_cg_steps=pst.cg_steps)
    t0 = time.perf_counter()
    cert = certify(op, R, spec.largest, dense, gap_tol, ctx.seed) if certify_result else None
    timings["certificate"] = time.perf_counter() - t0
    R, t, z = _finish(op, R, gauge, timings, t_start)
    lam_d1 = float(spec.smallest[op.d]) if op.M > 1 else spec.largest
    stats.update(
        lambda_d_plus_1=lam_d1,
        lambda_max=spec.largest,
        spectral_gap_ratio=lam_d1 / spec.largest,
        C_products=op.num_matvecs,
        laplacian=op.lap.method,
    )
    return SolveResult(
        rotations=R,
        translations=t,
        nodes=z,
        patch_names=list(problem.patch_names),
        objective=op.residual(R, t, z),
        iterations=run.iterations,
        converged=bool(run.converged),
        certificate=cert,
        solver=solver,
        method="dense" if dense else "matrix-free",
        history=[h if isinstance(h, dict) else h.__dict__ for h in run.history],
        timings=timings,
        stats=stats,
    )
