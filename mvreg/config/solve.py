"""Settings of the global solve (mvreg.solver.solve)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

# The solvers of mvreg.solver's registry (a test checks the two agree).
SOLVER_NAMES = ("reg-admm", "spectral", "gpm", "balm", "c-admm")


class SolveConfig(BaseModel):
    """The global stage (mvreg.solver.solve)."""

    model_config = ConfigDict(extra="forbid")

    solver: str = "reg-admm"
    method: Literal["auto", "dense", "matrix-free"] = "auto"
    rho: Literal["auto"] | float = "auto"
    max_iter: int = Field(500, ge=1)
    allow_reflections: bool = False

    @field_validator("solver")
    @classmethod
    def _known_solver(cls, name: str) -> str:
        if name not in SOLVER_NAMES:
            raise ValueError(f"unknown solver '{name}' (choose from {', '.join(SOLVER_NAMES)})")
        return name
