"""The contract between ``solve()`` and the global solvers, and the registry of solvers.

A solver is a module with a function ``run(ctx: SolverContext) -> SolverRun``.

It receives (``SolverContext``): the operator of the normalized data matrix C (products
``operator.matvec(V)`` for V (n, r), the dense C by ``operator.dense()`` when ``dense`` is
set, ``operator.d``, ``operator.M``, ``operator.n = M d``, ``operator.norm.scale``: data
units = normalized units x scale^2), the start rotations (M, d, d) (spectral by default),
the spectrum of C (its d+1 smallest eigenpairs and an upper bound on lambda_max(C)), its own
options (the section of ``SolveConfig`` named after it, ``-`` read as ``_``), the seed of
any random start, and a callback.

It must: call ``ctx.callback`` (when set) with one ``IterationRecord`` per iteration, the
objective in the problem's units; return rotations (M, d, d) in any gauge, with SO(d)
blocks unless ``ctx.allow_reflections``; be deterministic for a given context.

It may: Newton-polish and certify its own output (REG-ADMM does, at checkpoints, and stops
early once certified); it then sets ``SolverRun.checked`` and ``SolverRun.certificate``
and ``solve()`` uses them as they are. Otherwise ``solve()`` polishes the rotations (when
the solver's options say ``polish``) and certifies them.

Adding a solver: one module with ``run``, one line in ``SOLVERS`` below, one options model
in ``mvreg/config/solve.py`` (a field of ``SolveConfig`` named after the solver, and the
name in ``SOLVER_NAMES`` there). The registry names modules instead of importing them, so
this module imports nothing else of mvreg and listing the solvers loads no numerics.

Design notes and history: docs/design/solver.md.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class IterationRecord:
    """One iteration of a solver, as every callback and every history receives it.

    objective: Tr(C G) (or f(O)) at the iterate, in the problem's units.
    primal_residual, dual_residual, rho: the solver's feasibility and stationarity measures
    and its penalty parameter; None where the solver has no such quantity (documented in
    each solver's module). extra: further solver-specific values (JSON scalars).
    """

    iteration: int
    objective: float
    primal_residual: float | None = None
    dual_residual: float | None = None
    rho: float | None = None
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Flat dict: the fields above, then ``extra``'s items."""
        return {
            "iteration": self.iteration,
            "objective": self.objective,
            "primal_residual": self.primal_residual,
            "dual_residual": self.dual_residual,
            "rho": self.rho,
            **self.extra,
        }


@dataclass
class Spectrum:
    """The d+1 smallest eigenvalues of C (ascending), their vectors (n, d+1), lambda_max."""

    smallest: np.ndarray
    vectors: np.ndarray
    largest: float

    def lambda_d_plus_1(self, d: int) -> float:
        """lambda_{d+1}(C) (lambda_max when C has no more than d eigenvalues)."""
        return float(self.smallest[d]) if self.smallest.shape[0] > d else self.largest


@dataclass
class SolverContext:
    """What a solver may use: the data, facts ``solve()`` already computed, its options."""

    operator: Any  # the RegOperator of the normalized problem (see the module docstring)
    start: np.ndarray  # (M, d, d) start rotations R_world_patch
    spectrum: Spectrum
    dense: bool  # C may be formed (operator.dense()); otherwise only operator.matvec
    options: Any  # the solver's own options model (e.g. config.solve.GpmOptions)
    allow_reflections: bool = False  # O(d) instead of SO(d)
    seed: int = 0
    callback: Callable[[IterationRecord], None] | None = None
    certify: bool = True  # solve() reports a certificate (solvers that certify honour it)
    gap_tol: float = 1e-6  # certified when the relative suboptimality bound is below this

    def emit(self, rec: IterationRecord, history: list[IterationRecord]) -> None:
        """Append ``rec`` to ``history`` and hand it to the callback (if any)."""
        history.append(rec)
        if self.callback is not None:
            self.callback(rec)


@dataclass
class SolverRun:
    """What a solver returns.

    rotations: (M, d, d) R_world_patch, any gauge. history: one IterationRecord per
    iteration. stats: solver-specific statistics (JSON values), merged into the result's.
    checked: the solver polished and certified ``rotations`` itself; ``certificate`` is
    then their certificate (None when ``ctx.certify`` is off). rho_*: the penalty parameter
    of ADMM-type solvers (initial, final, and every change with its reason).
    timings: seconds, merged into the result's timings (e.g. "iterations", "polish").
    """

    rotations: np.ndarray
    iterations: int
    converged: bool
    history: list[IterationRecord] = field(default_factory=list)
    stats: dict = field(default_factory=dict)
    checked: bool = False
    certificate: Any = None
    rho_initial: float | None = None
    rho_final: float | None = None
    rho_history: list[dict] = field(default_factory=list)
    timings: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SolverEntry:
    """A registered solver: its name, the module holding ``run``, and what it is."""

    name: str
    module: str
    summary: str

    @property
    def options_field(self) -> str:
        """The field of SolveConfig holding this solver's options."""
        return self.name.replace("-", "_")

    def load(self) -> Callable[[SolverContext], SolverRun]:
        """The solver's ``run`` function (imports its module)."""
        return importlib.import_module(self.module).run


def _entries(*entries: SolverEntry) -> dict[str, SolverEntry]:
    return {e.name: e for e in entries}


# name -> solver, in the order they are listed to users. The first is the default.
SOLVERS: dict[str, SolverEntry] = _entries(
    SolverEntry("reg-admm", "mvreg.solver.reg_admm", "REG-ADMM, paper 000 eq. (7)"),
    SolverEntry("spectral", "mvreg.solver.spectral", "eigenvector method, paper 001 sec. 2"),
    SolverEntry("gpm", "mvreg.solver.gpm", "generalized power method, paper 001 Alg. 1"),
    SolverEntry("balm", "mvreg.solver.balm", "augmented Lagrangian, paper 002 sec. 3"),
    SolverEntry("c-admm", "mvreg.solver.c_admm", "ADMM on the convex relaxation C-SDP"),
)
