"""The global stage: patch problems, the data matrix C, REG-ADMM, certificates."""

from mvreg.solver.certificate import Certificate, certify
from mvreg.solver.operator import RegOperator
from mvreg.solver.problem import PatchProblem, load_problem, save_problem
from mvreg.solver.result import SolveResult
from mvreg.solver.solve import SOLVERS, solve

__all__ = [
    "SOLVERS",
    "Certificate",
    "PatchProblem",
    "RegOperator",
    "SolveResult",
    "certify",
    "load_problem",
    "save_problem",
    "solve",
]
