"""The global stage: patch problems, the data matrix C, the solvers, certificates.

Public API: ``solve(problem, config=None, *, init, seed, callback, operator, **overrides)
-> SolveResult``; the solver registry ``SOLVERS`` and the solver contract
(``SolverContext``, ``SolverRun``, ``IterationRecord``) in mvreg.solver.base; the settings
``SolveConfig`` (mvreg.config.solve). Design notes: docs/design/solver.md.
"""

from mvreg.config.solve import SolveConfig
from mvreg.solver.base import SOLVERS, IterationRecord, SolverContext, SolverRun, Spectrum
from mvreg.solver.certificate import Certificate, certify
from mvreg.solver.operator import RegOperator
from mvreg.solver.problem import PatchProblem, load_problem, save_problem
from mvreg.solver.result import SolveResult
from mvreg.solver.solve import solve

__all__ = [
    "SOLVERS",
    "Certificate",
    "IterationRecord",
    "PatchProblem",
    "RegOperator",
    "SolveConfig",
    "SolveResult",
    "SolverContext",
    "SolverRun",
    "Spectrum",
    "certify",
    "load_problem",
    "save_problem",
    "solve",
]
