"""How REG-ADMM's penalty rho is chosen and adapted (issue 15).

Two policies, both recorded change by change (``changes``: iteration, rho, previous,
reason):

``balanced`` (the default): start at lambda_max(C) / M, then residual balancing (Boyd et
al. 2011, sec. 3.4.1, in the relative form of OSQP): every ``window`` iterations compare
the relative primal residual ||bd(G) - I|| / ||I|| with the relative dual residual
rho ||H^{k+1} - H^k|| / ||bd(C G)|| and, when one exceeds the other by more than ``ratio``,
multiply rho by the square root of their quotient (at most ``max_factor`` per change),
within [Theorem 4's bound, lambda_max(C) / M]. The cap is the start: in the first tens of
iterations from a spectral start the primal residual grows while the cost falls (G leaves
the constraint set on its way to a better basin), and balancing that by raising rho froze
the iterates (rho 0.08 -> 4 in 20 iterations, not certified after 500 at M = 1,000 and 12%
noise; capped: certified at iteration 50). So the balancing only lowers rho, when the
dual residual dominates.

Why lambda_max(C) / M: the G-update takes the top-d eigenvectors of H - (C + Lambda) / rho.
Near a feasible H = X X^T (eigenvalue M on span X) that is one step of the generalized
power method (paper 001, Algorithm 1) on alpha I - C with alpha = rho M, and alpha =
lambda_max(C) is the smallest shift for which that step cannot increase the cost. A
smaller rho lets -C / rho swamp H: the top eigenvalues turn negative, G collapses to 0 and
the iteration stalls until rho has grown back (the first ~200 iterations of issue 15,
from Theorem 4's lambda_{d+1}(C) / (2 M sqrt(d)), ~1e-7 at M = 10,000). A much larger rho
makes the steps ~1/rho short.

``theorem4``: paper 000 Theorem 4's bound lambda_{d+1}(C) / (2 M sqrt(d)) (convergence from
a feasible start on clean data), doubled whenever the primal residual has not fallen below
0.99 x its best for ``window`` iterations (the oscillation of paper 000 sec. 2.6), up to
``rho_max``. The policy of the paper and of mvreg before issue 15.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


def theorem4_rho(lam_d1: float, m: int, d: int, h0_norm: float | None = None) -> float:
    """Theorem 4: rho <= lambda_{d+1}(C) / sqrt(||H0||^2 + 2 M sqrt(d) ||H0|| + M^2 d)."""
    h = m * math.sqrt(d) if h0_norm is None else h0_norm
    return lam_d1 / math.sqrt(h * h + 2 * m * math.sqrt(d) * h + m * m * d)


def balanced_rho(lam_max: float, m: int) -> float:
    """lambda_max(C) / M: the G-update is then a monotone power step (module docstring)."""
    return lam_max / m


@dataclass
class RhoPolicy:
    """rho for the next iteration from the residuals of the last ones (module docstring).

    primal: ||bd(G) - I||_F / sqrt(Md); dual: rho ||H^{k+1} - H^k||_F / ||bd(C G)||_F.
    """

    rho: float
    kind: str = "balanced"  # "balanced" | "theorem4" | "fixed"
    window: int = 10
    rho_min: float = 0.0
    rho_max: float = math.inf
    ratio: float = 5.0
    max_factor: float = 10.0
    changes: list[dict] = field(default_factory=list)
    _best: float = math.inf
    _best_at: int = 0

    def update(self, k: int, primal: float, dual: float) -> float:
        """Record iteration k's residuals; returns rho for iteration k + 1."""
        if self.kind == "theorem4":
            self._stall(k, primal)
        elif self.kind == "balanced" and k % self.window == 0:
            self._balance(k, primal, dual)
        return self.rho

    def _change(self, k: int, new: float, reason: str) -> None:
        self.changes.append({"iteration": k, "rho": new, "previous": self.rho, "reason": reason})
        self.rho = new

    def _stall(self, k: int, primal: float) -> None:
        if primal < 0.99 * self._best:
            self._best, self._best_at = primal, k
        elif k - self._best_at >= self.window and self.rho < self.rho_max:
            self._change(
                k,
                min(2.0 * self.rho, self.rho_max),
                f"primal residual stalled at {primal:.3g} for {self.window} iterations "
                "(oscillation, paper 000 sec. 2.6)",
            )
            self._best, self._best_at = primal, k

    def _balance(self, k: int, primal: float, dual: float) -> None:
        if not (primal > 0 and dual > 0 and math.isfinite(primal) and math.isfinite(dual)):
            return
        q = primal / dual
        if 1.0 / self.ratio <= q <= self.ratio:
            return
        f = min(max(math.sqrt(q), 1.0 / self.max_factor), self.max_factor)
        new = min(max(self.rho * f, self.rho_min), self.rho_max)
        if new == self.rho:
            return
        side = "primal" if q > 1 else "dual"
        self._change(
            k,
            new,
            f"residual balancing: relative primal {primal:.3g} vs dual {dual:.3g} "
            f"({side} residual larger by > {self.ratio:g}x)",
        )
