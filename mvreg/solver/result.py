"""SolveResult: what every solver returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mvreg.geometry import make_transform
from mvreg.solver.certificate import Certificate


@dataclass
class SolveResult:
    """Rotations, translations and node positions of a solved patch problem.

    rotations: (M, d, d) R_world_patch; translations: (M, d) t_world_patch, so that
    p_world = R p_local + t. The world frame is patch 0's frame (gauge), unless the
    caller asked otherwise. nodes: (N, d) node positions in world (in the order of
    ``problem.node_ids``).
    """

    rotations: np.ndarray
    translations: np.ndarray
    nodes: np.ndarray
    patch_names: list[str]
    objective: float
    iterations: int
    converged: bool
    certificate: Certificate | None
    solver: str
    method: str
    rho_initial: float | None = None
    rho_final: float | None = None
    rho_history: list[dict] = field(default_factory=list)
    history: list[dict] = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)

    @property
    def T_world_patch(self) -> np.ndarray:
        """(M, d+1, d+1) world_from_local transforms."""
        return np.stack(
            [make_transform(r, t) for r, t in zip(self.rotations, self.translations, strict=True)]
        )

    @property
    def certified(self) -> bool:
        return bool(self.certificate is not None and self.certificate.certified)

    def poses(self) -> dict[str, np.ndarray]:
        return dict(zip(self.patch_names, self.T_world_patch, strict=True))

    def summary(self) -> str:
        """One line: solver, size, iterations, time, objective, and the certificate; when not
        certified, the lower bound on the optimum and the relative gap it leaves."""
        c = self.certificate
        cert = "n/a" if c is None else ("yes" if c.certified else "NO")
        if c is not None and not c.certified:
            cert += (
                f" (optimum >= {c.lower_bound:.6g}: relative gap <= {c.relative_gap:.3g}, "
                f"min eigenvalue {c.min_eigenvalue:.3g})"
            )
        t = self.timings.get("total", float("nan"))
        return (
            f"{self.solver} ({self.method}): {len(self.patch_names)} patches, "
            f"{self.iterations} iterations, {t:.2f} s, objective {self.objective:.6g}, "
            f"certified {cert}"
        )

    def to_dict(self) -> dict:
        """Solver statistics for JSON (no arrays)."""
        return {
            "solver": self.solver,
            "method": self.method,
            "objective": self.objective,
            "iterations": self.iterations,
            "converged": self.converged,
            "rho_initial": self.rho_initial,
            "rho_final": self.rho_final,
            "rho_history": self.rho_history,
            "timings_s": self.timings,
            **self.stats,
        }

    def __repr__(self) -> str:
        c = self.certificate
        cert = (
            "None"
            if c is None
            else (
                f"certified={c.certified}, "
                f"min_eig{'>=' if c.eigen_method == 'inertia' else '='}{c.min_eigenvalue:.3g}, "
                f"kkt={c.kkt_residual:.2g}"
            )
        )
        return (
            f"SolveResult(solver={self.solver!r}, method={self.method!r}, "
            f"M={len(self.patch_names)}, "
            f"d={self.rotations.shape[-1]}, objective={self.objective:.6g}, "
            f"iterations={self.iterations}, converged={self.converged}, {cert}, "
            f"time={self.timings.get('total', float('nan')):.3f}s)"
        )
