"""C-ADMM: ADMM for the convex relaxation C-SDP (paper 000 Sec. 1.3; Sanyal et al. 2017).

    (C-SDP)   min Tr(C G)  s.t.  G PSD (Md x Md),  G_ii = I_d  (no rank constraint)

Iteration (the same augmented Lagrangian as REG-ADMM, eq. 6; only the G-update differs):

    G <- Pi_PSD(H - (C + Lambda)/rho)       eigendecomposition, negative eigenvalues
                                             clipped to 0 (all positive ones kept)
    H <- G with every diagonal d x d block set to I
    Lambda <- Lambda + rho (bd(G) - I)       (block diagonal, Prop. 3)

Dense only: one dense symmetric eigendecomposition of an Md x Md matrix per iteration,
O((Md)^3) time and O((Md)^2) memory. Pi_PSD needs exactly the eigenpairs with positive
eigenvalues (the negative ones are clipped to 0), so by default LAPACK syevr is asked for
the eigenvalues in (0, inf) only: the same projection as a full decomposition, and faster
(``full_eig=True`` computes all of them). Size limit: ``M d <= C_ADMM_MAX_N`` (1500);
larger problems are refused with a ConfigError.

Start: H0 = G0 = O0^T O0 from the initial rotations (spectral by default) and the dual
Lambda0 = -sym(bd(C G0)) (paper 000 Prop. 2's dual at G0).

rho: "auto" starts from sqrt(lambda_{d+1}(C) lambda_max(C)) / M (C's scale per unit
eigenvalue of G, G's eigenvalues being ~M; why this value: docs/design/solver.md) and is
then balanced
during the first ``balance_until`` (200) iterations (Boyd et al. 2011, Sec. 3.4.1): doubled
when the primal residual exceeds 10x the dual one, halved in the opposite case, at most
every ``balance_every`` (20) iterations. Balancing is then frozen, so the iteration is
plain ADMM with a fixed rho from there on (convergence for any rho > 0). A number fixes rho.

Stopping rule: relative primal residual ||bd(G) - I||_F / sqrt(Md) and relative dual
residual ||H_{k+1} - H_k||_F / ||H_k||_F both <= tol, or max_iter. Every ``gap_every`` (25)
iterations and at the end a duality gap is computed: the feasible point
G' = D^{-1/2} G D^{-1/2} (D = bd(G)) gives the upper bound Tr(C G'), and the dual Lambda
the lower bound -Tr(Lambda) + Md lambda_min(C + Lambda). Called directly (``c_admm``), the
run also stops when (upper - lower) <= tol * max(upper, 1e-12 lambda_max Md).

Through solve() (``run``, the registry entry) the duality-gap exit is replaced by a
certificate exit, checked at the same iterations once the primal residual is below 100 tol:
the top-d eigenvectors of G' are rounded to rotations and passed to the global-optimality
certificate (certificate.py, default gap tolerance); if they are certified, O^T O is the
optimum of C-SDP (rank d, the relaxation is tight) up to that tolerance, and C-ADMM stops
("stopped_by": "certificate"), typically well before both residuals reach tol.

Rank (tightness of the relaxation, paper 000 Fig. 3): the number of eigenvalues of the
final G' above ``rank_rtol`` (1e-3) times its largest eigenvalue (~M). rank == d means the
relaxation is tight: G' = O^T O is the global optimum of REG-SDP too. Rounding: the top-d
eigenvectors of G' scaled by sqrt(eigenvalue), each d x d block projected onto SO(d)/O(d).

Options: ``solve.c_admm`` (CAdmmOptions: max_iter, tol, polish, rho, gap_every,
balance_every, balance_until, balance, balance_ratio, full_eig, rank_rtol). Iteration
records: objective Tr(C G) in the problem's units, the primal and dual residuals above,
rho; extra: positive_eigenvalues, and upper / lower (problem units) where the gap was
computed. Design notes and measurements: docs/design/solver.md.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla

from mvreg.errors import ConfigError
from mvreg.solver.base import IterationRecord, SolverContext, SolverRun
from mvreg.solver.blocks import round_to_rotations, sym, x_from_rotations
from mvreg.solver.certificate import DEFAULT_GAP_TOL, certify

C_ADMM_MAX_N = 1500
RANK_RTOL = 1e-3


@dataclass
class CAdmmResult:
    G: np.ndarray  # feasible (diagonal blocks I) PSD optimum estimate, normalized units
    eigenvalues: np.ndarray  # of G, descending
    rank: int
    rotations: np.ndarray  # rounded (M, d, d)
    lam: np.ndarray  # dual blocks (M, d, d)
    iterations: int
    converged: bool
    stopped_by: str
    upper: float  # Tr(C G) at the feasible G (normalized units)
    lower: float  # dual lower bound (normalized units)
    rho_final: float
    history: list[IterationRecord] = field(default_factory=list)


def _bd(a: np.ndarray, m: int, d: int) -> np.ndarray:
    """Diagonal d x d blocks of a dense (n, n) matrix: (M, d, d)."""
    idx = np.arange(m)[:, None] * d + np.arange(d)[None, :]
    return a[idx[:, :, None], idx[:, None, :]]


def _set_bd(a: np.ndarray, blocks: np.ndarray, add: bool = False) -> None:
    m, d, _ = blocks.shape
    idx = np.arange(m)[:, None] * d + np.arange(d)[None, :]
    if add:
        a[idx[:, :, None], idx[:, None, :]] += blocks
    else:
        a[idx[:, :, None], idx[:, None, :]] = blocks


def check_size(n: int) -> None:
    if n > C_ADMM_MAX_N:
        raise ConfigError(
            f"c-admm is dense (a dense eigendecomposition of the Md x Md matrix per "
            f"iteration) and limited to M d <= {C_ADMM_MAX_N}; this problem has M d = {n}. "
            "Use reg-admm, gpm or balm for larger problems."
        )


def _feasible(G: np.ndarray, m: int, d: int) -> np.ndarray:
    """D^{-1/2} G D^{-1/2} with D = bd(G): PSD with identity diagonal blocks."""
    blocks = sym(_bd(G, m, d))
    w, v = np.linalg.eigh(blocks)
    w = np.maximum(w, 1e-12)
    isq = np.einsum("mab,mb,mcb->mac", v, 1.0 / np.sqrt(w), v)
    Gb = G.reshape(m, d, m, d)
    out = np.einsum("iab,ibjc,jdc->iajd", isq, Gb, isq).reshape(m * d, m * d)
    out = 0.5 * (out + out.T)
    _set_bd(out, np.broadcast_to(np.eye(d), (m, d, d)).copy())
    return out


def _bounds(C, G, lam, m, d, lam_max):
    """(upper, lower, G_feasible): primal value at a feasible point and the dual bound."""
    n = m * d
    Gf = _feasible(G, m, d)
    upper = float(np.sum(C * Gf))
    A = C.copy()
    _set_bd(A, lam, add=True)
    lmin = float(sla.eigh(A, eigvals_only=True, subset_by_index=[0, 0])[0])
    lower = -float(np.trace(lam, axis1=1, axis2=2).sum()) + n * lmin
    return upper, lower, Gf


def c_admm(
    C: np.ndarray,
    d: int,
    R0: np.ndarray,
    *,
    rho: str | float = "auto",
    lam_d1: float | None = None,
    lam_max: float | None = None,
    max_iter: int = 2000,
    tol: float = 1e-6,
    allow_reflections: bool = False,
    rank_rtol: float = RANK_RTOL,
    gap_every: int = 25,
    balance_every: int = 20,
    balance_until: int = 200,
    balance: str = "boyd",
    balance_ratio: float = 5.0,
    callback=None,
    full_eig: bool = False,
    certify_fn=None,
    objective_scale: float = 1.0,
) -> CAdmmResult:
    """Run C-ADMM on a dense normalized C (n, n). See the module docstring.

    History and callback: one IterationRecord per iteration, objective (and the bounds in
    ``extra``) in the units of C times ``objective_scale``.
    """
    n = C.shape[0]
    m = n // d
    check_size(n)
    if lam_max is None or lam_d1 is None:
        w = sla.eigh(C, eigvals_only=True)
        lam_max = float(w[-1]) if lam_max is None else lam_max
        lam_d1 = float(w[min(d, n - 1)]) if lam_d1 is None else lam_d1
    eye = np.eye(d)
    X0 = x_from_rotations(R0)
    H = X0 @ X0.T
    lam = -sym(_bd(C @ H, m, d))
    if rho == "auto":
        rho_v = math.sqrt(max(lam_d1, 1e-9 * lam_max) * lam_max) / m
        adaptive = balance_until > 0
    else:
        rho_v = float(rho)
        adaptive = False
    history = []
    converged = False
    stopped_by = "max_iter"
    G = H
    last_balance = 0
    upper = lower = math.nan
    Gf = None
    k = 0
    for k in range(1, max_iter + 1):
        A = H - C / rho_v
        _set_bd(A, -lam / rho_v, add=True)
        A = 0.5 * (A + A.T)
        if full_eig:
            w, V = sla.eigh(A, overwrite_a=True, check_finite=False)
        else:
            # The same projection, computing only the eigenpairs with eigenvalue > 0.
            w, V = sla.eigh(
                A, overwrite_a=True, check_finite=False, driver="evr", subset_by_value=(0, np.inf)
            )
        pos = w > 0
        Vp = V[:, pos]
        G = (Vp * w[pos]) @ Vp.T
        gd = _bd(G, m, d)
        resid = gd - eye
        H_new = G.copy()
        _set_bd(H_new, np.broadcast_to(eye, (m, d, d)).copy())
        pr = float(np.linalg.norm(resid)) / math.sqrt(n)
        dh = float(np.linalg.norm(H_new - H))
        dr = dh / max(float(np.linalg.norm(H)), 1e-300)
        lam = lam + rho_v * resid
        H = H_new
        rec = IterationRecord(
            k,
            float(np.sum(C * G)) * objective_scale,
            primal_residual=pr,
            dual_residual=dr,
            rho=rho_v,
            extra={
                "positive_eigenvalues": int(np.sum(w > rank_rtol * max(w[-1], 1e-300)))
                if w.size
                else 0
            },
        )
        if pr <= tol and dr <= tol:
            converged, stopped_by = True, "residuals"
        elif gap_every and k % gap_every == 0:
            upper, lower, Gf = _bounds(C, G, lam, m, d, lam_max)
            rec.extra.update(upper=upper * objective_scale, lower=lower * objective_scale)
            if certify_fn is None and upper - lower <= tol * max(upper, 1e-12 * lam_max * n):
                converged, stopped_by = True, "duality_gap"
            elif certify_fn is not None and pr <= 100.0 * tol:
                # Round the feasible iterate; if the rotations pass the global-optimality
                # certificate, O^T O is the C-SDP optimum (rank d) up to the certificate's gap.
                _, vd = sla.eigh(Gf, subset_by_index=[n - d, n - 1])
                if certify_fn(round_to_rotations(vd[:, ::-1] * math.sqrt(m), d, allow_reflections)):
                    converged, stopped_by = True, "certificate"
        history.append(rec)
        if callback is not None:
            callback(rec)
        if converged:
            break
        if adaptive and k <= balance_until and k - last_balance >= balance_every:
            if balance == "osqp":
                # OSQP-style: rho *= sqrt(relative primal / relative dual residual), applied
                # when the factor exceeds balance_ratio (either way).
                r_rel = pr * math.sqrt(n) / max(float(np.linalg.norm(H)), 1e-300)
                s_rel = rho_v * dh / max(float(np.linalg.norm(lam)), 1e-300)
                fac = math.sqrt(r_rel / max(s_rel, 1e-300))
                if fac > balance_ratio or fac < 1.0 / balance_ratio:
                    rho_v *= min(max(fac, 1e-3), 1e3)
                    last_balance = k
            else:
                # Boyd et al.: r = ||G - H||, s = rho ||H_{k+1} - H_k||.
                r_abs, s_abs = pr * math.sqrt(n), rho_v * dh
                if r_abs > 10.0 * s_abs:
                    rho_v *= 2.0
                    last_balance = k
                elif s_abs > 10.0 * r_abs:
                    rho_v /= 2.0
                    last_balance = k
    upper, lower, Gf = _bounds(C, G, lam, m, d, lam_max)
    if stopped_by == "certificate":
        # Proven optimum O^T O: rank d, eigenvalues M (d times) and 0.
        _, vd = sla.eigh(Gf, subset_by_index=[n - d, n - 1])
        Xc = x_from_rotations(round_to_rotations(vd[:, ::-1] * math.sqrt(m), d, allow_reflections))
        Gf = Xc @ Xc.T
        upper = float(np.sum(C * Gf))
    ev, evec = sla.eigh(Gf)
    ev, evec = ev[::-1], evec[:, ::-1]
    rank = int(np.sum(ev > rank_rtol * ev[0]))
    Xd = evec[:, :d] * np.sqrt(np.maximum(ev[:d], 0.0))
    R = round_to_rotations(Xd, d, allow_reflections)
    return CAdmmResult(
        G=Gf,
        eigenvalues=ev,
        rank=rank,
        rotations=R,
        lam=lam,
        iterations=k,
        converged=converged,
        stopped_by=stopped_by,
        upper=upper,
        lower=lower,
        rho_final=rho_v,
        history=history,
    )


def run(ctx: SolverContext) -> SolverRun:
    """Registry entry "c-admm": C-ADMM on the dense C from ctx.start, rounded rotations."""
    op, o = ctx.operator, ctx.options
    d, n, m = op.d, op.n, op.M
    check_size(n)  # before forming anything dense
    t0 = time.perf_counter()
    C = op.dense()
    lam_max = float(ctx.spectrum.largest)
    lam_d1 = float(ctx.spectrum.smallest[min(d, n - 1)])

    def certify_fn(R):
        return certify(op, R, lam_max, True, DEFAULT_GAP_TOL, ctx.seed).certified

    s2 = op.norm.scale**2
    res = c_admm(
        C,
        d,
        ctx.start,
        certify_fn=certify_fn,
        rho=o.rho,
        lam_d1=lam_d1,
        lam_max=lam_max,
        max_iter=o.max_iter,
        tol=o.tol,
        allow_reflections=ctx.allow_reflections,
        rank_rtol=o.rank_rtol,
        gap_every=o.gap_every,
        balance_every=o.balance_every,
        balance_until=o.balance_until,
        balance=o.balance,
        balance_ratio=o.balance_ratio,
        callback=ctx.callback,
        full_eig=o.full_eig,
        objective_scale=s2,
    )
    top = res.eigenvalues[: min(n, d + 3)] / m
    return SolverRun(
        rotations=res.rotations,
        iterations=res.iterations,
        converged=res.converged,
        history=res.history,
        stats={
            "rank": res.rank,
            "tight": res.rank == d,
            "rank_rtol": o.rank_rtol,
            "eigenvalues_over_M": [float(x) for x in top],
            "sdp_objective": res.upper * s2,
            "sdp_lower_bound": res.lower * s2,
            "sdp_relative_gap": (res.upper - res.lower) / max(abs(res.upper), 1e-12 * lam_max * n),
            "rounded": res.rank > d,
            "stopped_by": res.stopped_by,
            "rho_final": res.rho_final,
            "size_limit_Md": C_ADMM_MAX_N,
            "c_admm_time_s": time.perf_counter() - t0,
        },
    )
