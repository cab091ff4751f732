"""Registry of the solvers other than REG-ADMM, all behind ``solve(problem, solver=...)``.

A solver here is a function ``run(op, R0, ctx) -> GenericRun``: it gets the RegOperator
(normalized C, dense or matrix-free products through ``op.matvec`` / ``op.dense()``), the
initial rotations R0 (M, d, d) (spectral by default) and a SolverContext; it returns its
rotations. solve() then certifies them, recovers translations and fixes the gauge, exactly
as for REG-ADMM, so every solver returns the same SolveResult.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mvreg.solver.spectral import Spectrum


@dataclass
class SolverContext:
    """What a solver may use: options and facts solve() already computed."""

    dense: bool  # C is available as op.dense(); otherwise only op.matvec
    max_iter: int
    tol: float
    allow_reflections: bool
    spectrum: Spectrum  # d+1 smallest eigenpairs of C and lambda_max
    seed: int
    callback: Callable | None = None  # called with an IterationRecord per iteration
    rho: str | float = "auto"


@dataclass
class GenericRun:
    """Output of a solver: rotations (M, d, d) R_world_patch (any gauge)."""

    rotations: np.ndarray
    iterations: int
    converged: bool
    history: list = field(default_factory=list)  # IterationRecord-like dicts
    stats: dict = field(default_factory=dict)


def _spectral(op, R0: np.ndarray, ctx: SolverContext) -> GenericRun:
    """The eigenvector method (paper 001 sec. 2): R0 itself, which solve() computed."""
    return GenericRun(rotations=R0, iterations=0, converged=True)


# name -> run function. Other modules add theirs here (gpm, balm, c-admm).
GENERIC_SOLVERS: dict[str, Callable[..., GenericRun]] = {"spectral": _spectral}


def _gpm(op, R0: np.ndarray, ctx: SolverContext) -> GenericRun:
    """Generalized power method (paper 001 Algorithm 1): mvreg/solver/gpm.py."""
    from mvreg.solver.gpm import run_gpm

    return run_gpm(op, R0, ctx)


def _balm(op, R0: np.ndarray, ctx: SolverContext) -> GenericRun:
    """BALM augmented Lagrangian (paper 002 Sec. 3): mvreg/solver/balm.py."""
    from mvreg.solver.balm import run_balm

    return run_balm(op, R0, ctx)


def _c_admm(op, R0: np.ndarray, ctx: SolverContext) -> GenericRun:
    """ADMM for the convex relaxation C-SDP (paper 000 Sec. 1.3): mvreg/solver/c_admm.py."""
    from mvreg.solver.c_admm import run_c_admm

    return run_c_admm(op, R0, ctx)


GENERIC_SOLVERS.update({"gpm": _gpm, "balm": _balm, "c-admm": _c_admm})
