"""Settings of the global solve (mvreg.solver.solve)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class SolveConfig(BaseModel):
    """The global stage (mvreg.solver.solve)."""

    model_config = ConfigDict(extra="forbid")

    solver: str = "reg-admm"
    method: Literal["auto", "dense", "matrix-free"] = "auto"
    rho: Literal["auto"] | float = "auto"
    max_iter: int = Field(500, ge=1)
    allow_reflections: bool = False
