"""solve(): the one entry point of the global stage.

Takes a PatchProblem and a SolveConfig (or its fields as keyword overrides); returns a
SolveResult: rotations, translations and node positions (patch 0 = world frame unless
``gauge="none"``), the REG objective, the global-optimality certificate (unless
``certify=False``), the solver's iteration history and statistics.

    validate (SolveConfig, start) -> initialise (build C, spectrum, ill-posedness check,
    spectral start) -> run the registered solver (mvreg.solver.base.SOLVERS) ->
    polish / certify (unless the solver did) -> closed-form translations, gauge -> result.

Guarantees: deterministic for the same problem, configuration and seed; one BLAS thread
(recorded in ``stats["blas_threads"]``); raises ConfigError for bad settings and
IllPosedError when lambda_{d+1}(C) ~ 0 (some rotation not determined by the data).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mvreg.config.solve import SolveConfig, solve_config
from mvreg.errors import ConfigError, IllPosedError
from mvreg.solver.base import SOLVERS, IterationRecord, SolverContext, SolverRun, Spectrum
from mvreg.solver.certificate import certify, inertia_shift
from mvreg.solver.operator import RegOperator
from mvreg.solver.polish import polish
from mvreg.solver.problem import PatchProblem
from mvreg.solver.result import SolveResult
from mvreg.solver.spectral import spectral_rotations, spectrum

# Dense (exact eigendecomposition per iteration) up to this M d; matrix-free above.
DENSE_MAX_N = 900
# lambda_{d+1}(C) / lambda_max(C) below this: some rotation is not determined.
ILL_POSED_RATIO = 1e-10
# solve() runs with one BLAS thread (docs/design/solver.md).
BLAS_THREADS = 1


def solve(
    problem: PatchProblem,
    config: SolveConfig | None = None,
    *,
    init: np.ndarray | str = "spectral",
    seed: int = 0,
    callback: Callable[[IterationRecord], None] | None = None,
    operator: RegOperator | None = None,
    **overrides,
) -> SolveResult:
    """Solve REG for a patch problem: rotations, translations, nodes, certificate.

    Args:
        problem: the PatchProblem.
        config: a SolveConfig (default: defaults). ``overrides`` are its fields
            (``solver="gpm"``, ``method="dense"``, ``allow_reflections=True``, ...) or the
            shared iteration keys ``rho``, ``max_iter``, ``tol``, ``polish``, which apply to
            every solver that has them (see mvreg.config.solve).
        init: "spectral" or rotations (M, d, d) R_world_patch to start from.
        seed: seeds the random starts of the iterative eigensolvers.
        callback: called with an IterationRecord after every iteration of the solver.
        operator: a prebuilt RegOperator for this problem (warm restarts).
    """
    from threadpoolctl import threadpool_limits

    cfg = solve_config(config, **overrides)
    with threadpool_limits(limits=BLAS_THREADS, user_api="blas"):
        res = _solve(problem, cfg, init, seed, callback, operator)
    res.stats["blas_threads"] = BLAS_THREADS
    return res


@dataclass
class _Setup:
    """What initialisation produced: the operator, its spectrum, the start, timings."""

    op: RegOperator
    dense: bool
    spec: Spectrum
    start: np.ndarray
    t_start: float
    timings: dict = field(default_factory=dict)


def _solve(problem, cfg: SolveConfig, init, seed, callback, operator) -> SolveResult:
    setup = _initialise(problem, cfg, init, seed, operator)
    ctx = SolverContext(
        operator=setup.op,
        start=setup.start,
        spectrum=setup.spec,
        dense=setup.dense,
        options=cfg.options(),
        allow_reflections=cfg.allow_reflections,
        seed=seed,
        callback=callback,
        certify=cfg.certify,
        gap_tol=cfg.gap_tol,
    )
    t0 = time.perf_counter()
    run = SOLVERS[cfg.solver].load()(ctx)
    setup.timings["iterations"] = time.perf_counter() - t0
    setup.timings.update(run.timings)
    R, cert = _polish_and_certify(run, ctx, setup.timings)
    R, t, z = _translations_and_gauge(setup.op, R, cfg.gauge, setup.timings)
    setup.timings["total"] = time.perf_counter() - setup.t_start
    return _result(problem, cfg, setup, run, R, t, z, cert)


def _initialise(problem, cfg: SolveConfig, init, seed, operator) -> _Setup:
    """Build C, its spectrum, check well-posedness, and the start rotations."""
    t_start = time.perf_counter()
    op = operator if operator is not None else RegOperator(problem)
    d, m = op.d, op.M
    dense = cfg.method == "dense" or (cfg.method == "auto" and op.n <= DENSE_MAX_N)
    timings = {"build_C": time.perf_counter() - t_start}
    t0 = time.perf_counter()
    spec = spectrum(op, dense=dense, seed=seed)
    lam_max, lam_d1 = spec.largest, spec.lambda_d_plus_1(d)
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
        R0 = spectral_rotations(spec, d, cfg.allow_reflections)
    else:
        R0 = np.asarray(init, dtype=np.float64)
        if R0.shape != (m, d, d) or not np.all(np.isfinite(R0)):
            raise ConfigError(f"init rotations must have shape {(m, d, d)} and be finite")
    timings["init"] = time.perf_counter() - t0
    return _Setup(op, dense, spec, R0, t_start, timings)


def _polish_and_certify(run: SolverRun, ctx: SolverContext, timings: dict):
    """(rotations, certificate): the solver's own when it checked them, else its rotations
    Newton-polished (when its options say so) and certified (when asked)."""
    if run.checked:
        return run.rotations, run.certificate
    op, lam_max, R = ctx.operator, ctx.spectrum.largest, run.rotations
    if ctx.options.polish:
        t0 = time.perf_counter()
        R, pst = polish(op, R, lam_max, ctx.allow_reflections)
        timings["polish"] = time.perf_counter() - t0
        run.stats.update(newton_steps=pst.newton_steps, newton_cg_steps=pst.cg_steps)
    t0 = time.perf_counter()
    tau = inertia_shift(ctx.spectrum.smallest, op.d)
    cert = None
    if ctx.certify:
        cert = certify(op, R, lam_max, ctx.dense, ctx.gap_tol, ctx.seed, tau=tau)
    timings["certificate"] = time.perf_counter() - t0
    return R, cert


def _translations_and_gauge(op: RegOperator, R: np.ndarray, gauge: str, timings: dict):
    """Closed-form translations and nodes for R, then the gauge (patch 0 = world)."""
    t0 = time.perf_counter()
    t, z = op.translations(R)
    if gauge == "first":
        r0, t0v = R[0].copy(), t[0].copy()
        R = np.einsum("ba,mbc->mac", r0, R)
        t = (t - t0v) @ r0
        z = (z - t0v) @ r0
    timings["translations"] = time.perf_counter() - t0
    return R, t, z


def _result(problem, cfg: SolveConfig, setup: _Setup, run: SolverRun, R, t, z, cert):
    op, spec = setup.op, setup.spec
    lam_d1 = spec.lambda_d_plus_1(op.d)
    return SolveResult(
        rotations=R,
        translations=t,
        nodes=z,
        patch_names=list(problem.patch_names),
        objective=op.residual(R, t, z),
        iterations=run.iterations,
        converged=bool(run.converged),
        certificate=cert,
        solver=cfg.solver,
        method="dense" if setup.dense else "matrix-free",
        rho_initial=run.rho_initial,
        rho_final=run.rho_final,
        rho_history=run.rho_history,
        history=[r.to_dict() for r in run.history],
        timings=setup.timings,
        stats={
            "lambda_d_plus_1": lam_d1,
            "lambda_max": spec.largest,
            "spectral_gap_ratio": lam_d1 / spec.largest,
            **run.stats,
            "C_products": op.num_matvecs,
            "laplacian": op.lap.method,
            "laplacian_cg_iterations": op.lap.cg_iterations,
            "paths": dict(op.paths),
            "factor_forecast": op.factor_forecast,
        },
    )
