"""Settings of the global solve (mvreg.solver.solve): shared fields and one model per solver.

Pure data: imports only pydantic and mvreg.errors. ``SOLVER_NAMES`` lists the registered
solvers (a test checks it equals the keys of ``mvreg.solver.base.SOLVERS``); ``SolveConfig``
checks the solver name once. Each solver reads its own section, named after it with ``-``
read as ``_`` (``solve.reg_admm.rho``, ``solve.gpm.max_iter``, ...).

The shared keys ``rho``, ``max_iter``, ``tol`` and ``polish`` may also be given at the top
of the section (``solve.max_iter=50``, ``solve(problem, rho=5.0)``): they are copied into
every solver section that has that field, overriding its value there. None means "not
given". After validation they live only in the sections. Design notes: docs/design/solver.md.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from mvreg.errors import ConfigError

# The registered solvers, in the order of mvreg.solver.base.SOLVERS (the first is the default).
SOLVER_NAMES = ("reg-admm", "spectral", "gpm", "balm", "c-admm")
# Keys accepted at the top of the solve section and copied into the solver sections.
SHARED_KEYS = ("rho", "max_iter", "tol", "polish")

Rho = Literal["auto"] | Annotated[float, Field(gt=0, allow_inf_nan=False)]


class SolverOptions(BaseModel):
    """Base of the per-solver options: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid")

    polish: bool = Field(
        False, description="Newton-polish the solver's rotations to a KKT point before certifying"
    )


class IterativeOptions(SolverOptions):
    """Options every iterative solver has."""

    max_iter: int = Field(500, ge=1, description="iteration cap")
    tol: float = Field(1e-6, gt=0, lt=1, description="relative stopping tolerance")


class SpectralOptions(SolverOptions):
    """The eigenvector method (mvreg.solver.spectral): no iterations of its own."""


class RegAdmmOptions(IterativeOptions):
    """REG-ADMM (mvreg.solver.reg_admm)."""

    rho: Rho = Field("auto", description="'auto' (see rho_policy) or a fixed rho > 0")
    rho_policy: Literal["balanced", "theorem4"] = Field(
        "balanced",
        description="rho='auto': 'balanced' starts at lambda_max(C)/M and balances the "
        "residuals; 'theorem4' starts at Theorem 4's bound and doubles on stalls",
    )
    dual_start: Literal["zero", "multipliers"] = Field(
        "zero",
        description="Lambda when iterating: 0 (paper 000) or the multipliers -bd(C G) of "
        "the start (Prop. 2)",
    )
    staircase_rounds: int = Field(
        3,
        ge=0,
        le=100,
        description="Riemannian-staircase steps from a point whose certificate fails with "
        "negative curvature (needs polish)",
    )
    balance_window: int = Field(
        5, ge=1, description="rho_policy='balanced': residuals compared every k iterations"
    )
    polish: bool = Field(
        True,
        description="Newton-polish and certify rounded iterates at checkpoints, stop once "
        "certified; False runs plain eq. (7) to its residual tolerance",
    )
    lobpcg_steps: int = Field(
        4, ge=1, le=1000, description="warm-started LOBPCG steps per iteration"
    )
    stall_window: int = Field(
        10, ge=1, description="rho_policy='theorem4' doubles rho after this many stalled iterations"
    )


class GpmOptions(IterativeOptions):
    """The generalized power method (mvreg.solver.gpm)."""


class BalmOptions(IterativeOptions):
    """The BALM augmented Lagrangian method (mvreg.solver.balm)."""

    mu0: float | None = Field(None, gt=0, description="initial penalty (None: lambda_{d+1}(C))")
    gamma: float = Field(2.0, gt=1, description="penalty increase factor")
    eta: float = Field(0.25, gt=0, lt=1, description="sufficient decrease of the consensus")
    inner_max: int = Field(
        50, ge=1, le=100_000, description="Gauss-Seidel sweeps per outer iteration"
    )
    inner_tol: float | None = Field(None, gt=0, description="None: adaptive")
    mu_max_factor: float = Field(10.0, gt=0, description="mu stops at this x lambda_max(C)")
    inner_rel: float = Field(0.1, gt=0, description="adaptive inner tolerance / KKT residual")
    cg_rtol: float = Field(1e-10, gt=0, description="block CG tolerance (matrix-free)")
    cg_maxiter: int = Field(
        500, ge=1, le=1_000_000, description="block CG iteration cap (matrix-free)"
    )


class CAdmmOptions(IterativeOptions):
    """ADMM on the convex relaxation C-SDP (mvreg.solver.c_admm); dense only."""

    rho: Rho = Field("auto", description="'auto' (balanced early on) or a fixed rho > 0")
    gap_every: int = Field(25, ge=0, description="duality gap / certificate every k iterations")
    balance_every: int = Field(20, ge=1)
    balance_until: int = Field(200, ge=0)
    balance: Literal["boyd", "osqp"] = "boyd"
    balance_ratio: float = Field(5.0, gt=1)
    full_eig: bool = Field(False, description="full eigendecomposition (else positive part)")
    rank_rtol: float = Field(1e-3, gt=0, lt=1, description="rank: eigenvalues above this x max")


class SolveConfig(BaseModel):
    """The global stage (mvreg.solver.solve): shared settings and one section per solver."""

    model_config = ConfigDict(extra="forbid")

    solver: str = Field("reg-admm", description="one of SOLVER_NAMES")
    method: Literal["auto", "dense", "matrix-free"] = Field(
        "auto", description="dense: exact eigensolvers; matrix-free: memory linear in M"
    )
    allow_reflections: bool = Field(False, description="O(d) instead of SO(d)")
    certify: bool = Field(True, description="compute the global-optimality certificate")
    gap_tol: float = Field(
        1e-6, gt=0, description="certified when the relative suboptimality bound is below"
    )
    gauge: Literal["first", "none"] = Field("first", description="first: patch 0 = world")
    reg_admm: RegAdmmOptions = Field(default_factory=RegAdmmOptions)
    spectral: SpectralOptions = Field(default_factory=SpectralOptions)
    gpm: GpmOptions = Field(default_factory=GpmOptions)
    balm: BalmOptions = Field(default_factory=BalmOptions)
    c_admm: CAdmmOptions = Field(default_factory=CAdmmOptions)

    @model_validator(mode="before")
    @classmethod
    def _copy_shared_keys(cls, data: Any) -> Any:
        if not isinstance(data, dict) or not any(k in data for k in SHARED_KEYS):
            return data
        shared = {k: data[k] for k in SHARED_KEYS if data.get(k) is not None}
        data = {k: v for k, v in data.items() if k not in SHARED_KEYS}
        for name in SOLVER_NAMES:
            key = _section(name)
            section = data.get(key, {})
            section = section.model_dump() if isinstance(section, BaseModel) else dict(section)
            fields = cls.model_fields[key].annotation.model_fields
            section.update({k: v for k, v in shared.items() if k in fields})
            data[key] = section
        return data

    @field_validator("solver")
    @classmethod
    def _known_solver(cls, name: str) -> str:
        if name not in SOLVER_NAMES:
            raise ValueError(f"unknown solver '{name}' (choose from {', '.join(SOLVER_NAMES)})")
        return name

    def options(self, name: str | None = None) -> SolverOptions:
        """The options of solver ``name`` (default: the chosen solver)."""
        return getattr(self, _section(self.solver if name is None else name))


def _section(name: str) -> str:
    return name.replace("-", "_")


def solve_config(config: SolveConfig | None = None, **overrides) -> SolveConfig:
    """``config`` (default: defaults) with ``overrides`` (SolveConfig fields, or the shared
    keys above) applied and validated. Raises ConfigError naming the bad field."""
    if config is not None and not isinstance(config, SolveConfig):
        raise TypeError(
            f"config must be a SolveConfig, got {type(config).__name__} (pass the solver "
            "as solver=...)"
        )
    if not overrides:
        return config if config is not None else SolveConfig()
    data = config.model_dump() if config is not None else {}
    data.update(overrides)
    try:
        return SolveConfig.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"]) or "solve"
        msg = err["msg"].removeprefix("Value error, ")
        raise ConfigError(
            f"solve.{where}: {msg}" + (f" (got {err['input']!r})" if "input" in err else "")
        ) from None
