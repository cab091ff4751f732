"""The best point of an iterative run: polished, certified, and escaped from when rejected.

REG-ADMM (reg_admm.py) hands its rounded iterates to ``BestPoint.check`` at checkpoints
(the start, then iterations 1, 2, 5, 10, 20, 50, ...): each is Newton-polished (and, when
one polish pass stops short of a KKT point and the certificate fails, polished further,
polish.repolish), certified, and kept if it is cheaper than the best so far.
``BestPoint.escape`` takes Riemannian-staircase steps (staircase.py) from the best point
while its certificate shows a direction of negative curvature. Design notes:
docs/design/solver.md.
"""

from __future__ import annotations

import time

import numpy as np

from mvreg.solver.base import SolverContext
from mvreg.solver.certificate import EIG_TOL, certify, inertia_shift
from mvreg.solver.polish import KKT_TOL, polish, repolish
from mvreg.solver.staircase import escape, lifted_descent, lifted_lower_bound

BOUND_STEPS = 1000
"""Further lifted descent steps before the lower bound at a lifted point is computed."""

LIFTED_GAP_STOP = 1e-3
"""When the lower bound from a lifted staircase point leaves a relative gap below this, the
best point cannot be bettered by more than that fraction of its cost: REG-ADMM's
iterations are skipped (``BestPoint.bounded``) and the answer is the best point with that
bound (issue 15: "certified or a reported gap <= 1e-3"). Random graph, M = 10,000, 8%
noise: the eigensolver's residual alone limits the bound to a gap of ~5e-4 there."""

SHORT_OF_KKT = 1e-8
"""A polished point with a larger KKT residual (polish.PolishStats.kkt_residual) is
polished further before it is certified."""


class BestPoint:
    """The best Newton-polished rounded iterate seen so far and its certificate.

    ``check(k, R)`` polishes R; if that reaches a lower cost than before it is certified
    and kept. Returns True once a kept point is certified.
    """

    def __init__(self, ctx: SolverContext):
        self.ctx = ctx
        self.lam_max = ctx.spectrum.largest
        self.R = None
        self.f = np.inf
        self.cert = None
        self.polish = None
        self.at = None
        self.t_polish = 0.0
        self.t_cert = 0.0
        self.t_escape = 0.0
        self.escapes: list[dict] = []
        # The best lower bound on the optimum from a lifted point (normalized units).
        self.lifted_bound = -np.inf
        self._lifted_cost = np.inf

    @property
    def certified(self) -> bool:
        return self.cert is not None and self.cert.certified

    def _polish(self, R):
        t0 = time.perf_counter()
        out = polish(self.ctx.operator, R, self.lam_max, self.ctx.allow_reflections)
        self.t_polish += time.perf_counter() - t0
        return out

    def _repolish(self, R, stats):
        t0 = time.perf_counter()
        c = self.ctx
        out = repolish(c.operator, R, stats, self.lam_max, c.allow_reflections)
        self.t_polish += time.perf_counter() - t0
        return out

    def _certify(self, R, inverse):
        t0 = time.perf_counter()
        c = self.ctx
        cert = (
            certify(
                c.operator,
                R,
                self.lam_max,
                c.dense,
                c.gap_tol,
                c.seed,
                inverse=inverse,
                tau=inertia_shift(c.spectrum.smallest, c.operator.d),
            )  # fmt: skip
            if c.certify
            else None
        )
        self.t_cert += time.perf_counter() - t0
        return cert

    def check(self, k: int, R: np.ndarray) -> bool:
        Rp, pst = self._polish(R)
        if pst.objective >= self.f - 1e-12 * max(abs(self.f), 1e-300):
            return False  # same stationary point as before: already checked
        # A polish that stopped well short of a KKT point (residual ~1e-4 where the start
        # was not yet in the basin; ~1e-16 where it converged) is not certified first: the
        # certificate fails there (M = 1,000, noise 0.04-0.08, both overlap graphs), and
        # costs as much as a Newton pass.
        cert = self._certify(Rp, pst.inverse) if pst.kkt_residual <= SHORT_OF_KKT else None
        if not (cert is not None and cert.certified) and pst.kkt_residual > KKT_TOL:
            # Polish stopped short of a KKT point (polish.repolish): finish, then certify.
            Rp, pst = self._repolish(Rp, pst)
            cert = self._certify(Rp, pst.inverse)
        pst.inverse = None  # free the factorization
        self.R, self.f, self.cert, self.polish, self.at = Rp, pst.objective, cert, pst, k
        return self.certified

    def finish(self, R_final: np.ndarray, iterations: int, polishing: bool) -> None:
        """After the iterations: polish the last iterate (when polishing) and certify the
        best point unless a checkpoint already did."""
        if polishing:
            Rp, pst = self._repolish(*self._polish(R_final))
            if pst.objective < self.f:
                self.R, self.f, self.polish, self.at = Rp, pst.objective, pst, iterations
                self.cert = None
        elif self.R is None:
            self.R, self.at = R_final, iterations
        if self.R is R_final or self.cert is None:
            inv = self.polish.inverse if self.polish is not None else None
            self.cert = self._certify(self.R, inv)

    @property
    def bounded(self) -> bool:
        """Whether a lifted lower bound leaves a relative gap below LIFTED_GAP_STOP."""
        return self.cert is not None and self._lifted_gap() <= LIFTED_GAP_STOP

    def _lifted_gap(self) -> float:
        f = self.cert.objective / self.ctx.operator.norm.scale**2
        return (f - self.lifted_bound) / f if f > 0 else np.inf

    def apply_lifted_bound(self) -> None:
        """Where the best point is not certified, a lifted point's lower bound that beats the
        certificate's own replaces it (``bound_source`` "lifted")."""
        c = self.cert
        if c is None or c.certified or not np.isfinite(self.lifted_bound):
            return
        lb = self.lifted_bound * self.ctx.operator.norm.scale**2
        if lb <= c.lower_bound:
            return
        c.lower_bound = lb
        c.suboptimality_bound = max(0.0, c.objective - lb)
        c.relative_gap = c.suboptimality_bound / max(c.objective, 1e-300)
        c.bound_source = "lifted"

    def _bound_from(self, st, rec: dict, r: int) -> None:
        """The lower bound at the escape's lifted point, when its cost is the lowest so far:
        the descent continued first (``BOUND_STEPS`` more, stopping only when its cost stops
        falling), since the bound is tight only near the lifted optimum (the escape's own
        descent stops earlier, at a point good enough to round from)."""
        c = self.ctx
        if st.lifted is None or not st.lifted_cost < self._lifted_cost:
            return
        t0 = time.perf_counter()
        Y, f_y, steps = lifted_descent(
            c.operator, st.lifted, c.operator.d, self.lam_max, BOUND_STEPS, 0.0
        )
        self._lifted_cost = f_y
        lb = lifted_lower_bound(c.operator, Y, self.lam_max, c.seed + r)[0]
        self.t_escape += time.perf_counter() - t0
        self.lifted_bound = max(self.lifted_bound, lb)
        rec["lifted_lower_bound"] = lb * c.operator.norm.scale**2
        rec["bound_descent_steps"] = steps

    def escape(self, rounds: int) -> bool:
        """Up to ``rounds`` staircase steps from the best point while its certificate shows
        negative curvature; each result is polished, certified and kept when cheaper.
        Returns True once certified."""
        c = self.ctx
        for r in range(rounds - len(self.escapes)):
            if self.certified or self.cert is None or self.cert.min_eigenvalue >= -EIG_TOL:
                break
            t0 = time.perf_counter()
            R2, st = escape(c.operator, self.R, self.lam_max, c.allow_reflections, c.seed + r)
            self.t_escape += time.perf_counter() - t0
            rec = {"min_eigenvalue": st.min_eigenvalue, "step": st.step}
            rec.update(lifted_iterations=st.iterations, from_objective=self.cert.objective)
            self.escapes.append(rec)
            if R2 is None:
                break
            Rp, pst = self._repolish(*self._polish(R2))
            rec["objective"] = pst.objective * c.operator.norm.scale**2
            if pst.objective >= self.f - 1e-12 * max(abs(self.f), 1e-300):
                # No cheaper point (beyond rounding; the same point polished again came out
                # 6e-15 cheaper at random M = 10,000, 8%): stop climbing.
                self._bound_from(st, rec, r)
                break
            cert = self._certify(Rp, pst.inverse)
            if not cert.certified:
                self._bound_from(st, rec, r)
            pst.inverse = None
            self.R, self.f, self.cert, self.polish = Rp, pst.objective, cert, pst
            rec["certified"] = self.certified
        return self.certified
