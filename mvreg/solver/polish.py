"""Riemannian Newton polish on SO(d)^M (or O(d)^M) for f(X) = Tr(X^T C X).

REG-ADMM converges only linearly; near its limit we finish with Newton steps, whose
fixed points are exactly the KKT points of O-REG (Lemma 1): the Riemannian gradient is
(C + Lambda) X and the Riemannian Hessian is P_X (C xi - xi M), xi in the tangent space.
Each Newton system is solved by truncated conjugate gradients (one product with C per
CG step), preconditioned by the exact Newton system at the starting point, factorized once
as a sparse LU (shift_invert.NewtonSystem): the first step is exact, later ones take a few
CG steps.
A backtracking line search keeps the cost decreasing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mvreg.geometry import project_to_orthogonal
from mvreg.solver.blocks import rotations_from_x, sym, x_from_rotations
from mvreg.solver.certificate import multipliers
from mvreg.solver.shift_invert import (
    SHIFT,
    NewtonSystem,
    ShiftedInverse,
    direct_feasible,
    krylov_first,
    newton_direct_feasible,
    skew_basis,
)

# Newton stops when ||grad||_F / (lambda_max sqrt(n)) is below this (~ the rounding floor).
KKT_TOL = 1e-14
# Where the factorization is forecast nearly dense (shift_invert.krylov_first) each Newton
# system is first solved by block-Jacobi CG with at most this many steps; a system that
# needs more falls back to the factorization (random overlap graph, M = 1,000: 30-45 CG
# steps per Newton step, against one factorization of ~1.5 s).
KRYLOV_CG_CAP = 150
STALLED = "factorization (block-jacobi CG stalled)"


@dataclass
class PolishStats:
    newton_steps: int
    cg_steps: int
    kkt_residual: float  # ||grad||_F / (lambda_max sqrt(n))
    objective: float  # normalized units
    # The (C + Lambda + sigma I)^{-1} used as preconditioner on large problems (reused by
    # the certificate), else None.
    inverse: object = field(default=None, repr=False)


def _tangent_project(xb: np.ndarray, zb: np.ndarray) -> np.ndarray:
    return zb - xb @ sym(np.einsum("mba,mbc->mac", xb, zb))


def _horizontal(xb: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Remove the gauge components (xi_i = X_i W, one W for all patches) of tangent z (n, d).

    Newton works on the quotient by global rotations: away from a critical point the
    Hessian is not exactly singular along the gauge, and CG must not chase that part.
    """
    m, d, _ = xb.shape
    zb = z.reshape(m, d, d)
    w = np.einsum("mba,mbc->ac", xb, zb) / m  # mean of X_i^T z_i
    w = 0.5 * (w - w.T)
    return (zb - xb @ w).reshape(-1, d)


def tangent_block_jacobi(op, xb: np.ndarray, mi: np.ndarray):
    """Block-Jacobi preconditioner of the Riemannian Hessian where no factorization is
    affordable: per patch, the Hessian restricted to its own tangent directions
    xi_i = X_i Omega (Omega skew), h_ab = <X_i E_a, Cd_i X_i E_b - X_i E_b M_i> with Cd_i the
    diagonal block of C0, made positive definite (eigenvalues by magnitude, floored).
    Returns prec(g) = -P g, the form of a Newton step that :func:`_precondition` takes."""
    d = op.d
    e = skew_basis(d)  # (k, d, d)
    g_loc = np.einsum("mba,mbc,mcd->mad", xb, op.diagonal_blocks(), xb)  # X_i^T Cd_i X_i
    h = np.einsum("apq,mpr,brq->mab", e, g_loc, e) - np.einsum("apq,bpr,mrq->mab", e, e, mi)
    w, v = np.linalg.eigh(0.5 * (h + h.transpose(0, 2, 1)))
    w = np.abs(w)
    w = np.maximum(w, 1e-8 * max(float(w.max()), 1e-300))
    h_inv = np.einsum("mab,mb,mcb->mac", v, 1.0 / w, v)

    e_flat = e.reshape(e.shape[0], d * d)
    xt = np.ascontiguousarray(xb.transpose(0, 2, 1))

    def prec(g):
        # As batched matrix products (three-operand einsums are ~10x slower here).
        coef = (xt @ g.reshape(-1, d, d)).reshape(-1, d * d) @ e_flat.T  # <X_i E_a, g_i>
        om = np.einsum("mab,mb->ma", h_inv, coef)
        return -(xb @ (om @ e_flat).reshape(-1, d, d)).reshape(g.shape)

    return prec


def _precondition(prec, xb: np.ndarray, r: np.ndarray) -> np.ndarray:
    """z ~ Hess^{-1} r on the horizontal space; prec(g) returns the Newton step -Hess0^{-1} g."""
    if prec is None:
        return r
    d = xb.shape[-1]
    return _horizontal(xb, _tangent_project(xb, (-prec(r)).reshape(-1, d, d)).reshape(-1, d))


def _newton_cg(hess, prec, xb, g, rel_grad, lam_max, max_cg):
    """Truncated CG on H xi = -g (horizontal tangent space), preconditioned by ``prec``;
    stops on negative curvature, at the forcing tolerance min(0.01, ``rel_grad``) relative,
    on stagnation (the rounding floor of the products with C) or after ``max_cg`` steps.
    Returns (xi, steps, capped: ran all ``max_cg`` steps without stopping otherwise)."""
    xi = np.zeros_like(g)
    r = -_horizontal(xb, g)
    z = _precondition(prec, xb, r)
    p = z.copy()
    rz = float(np.sum(r * z))
    stop = float(np.sum(r * r)) * min(0.01, rel_grad) ** 2
    steps = 0
    best_rr, since_best = np.inf, 0
    for _ in range(max_cg):
        hp = hess(p)
        steps += 1
        php = float(np.sum(p * hp))
        if php <= 1e-14 * lam_max * float(np.sum(p * p)):
            if not np.any(xi):
                xi = -g
            break
        alpha = rz / php
        xi += alpha * p
        r -= alpha * hp
        rr = float(np.sum(r * r))
        if rr <= stop:
            break
        # Stagnation: rounding errors in the products with C set a floor on the residual.
        best_rr, since_best = (rr, 0) if rr < 0.5 * best_rr else (best_rr, since_best + 1)
        if since_best >= 30:
            break
        z = _precondition(prec, xb, r)
        rz_new = float(np.sum(r * z))
        if rz_new <= 0.0 or rz <= 0.0:
            break  # exact solve, or an indefinite preconditioner: stop here
        p = z + (rz_new / rz) * p
        rz = rz_new
    else:
        return xi, steps, True
    return xi, steps, False


def polish(
    op,
    R: np.ndarray,
    lam_max: float,
    allow_reflections: bool = False,
    kkt_tol: float = KKT_TOL,
    max_newton: int = 25,
    max_cg: int = 500,
    precondition: bool = True,
) -> tuple[np.ndarray, PolishStats]:
    """Newton-refine rotations R (M, d, d) to a KKT point. Returns (R, stats).

    Preconditioner: the exact Newton system at the start (one sparse factorization) when
    affordable; on larger problems (C + Lambda + sigma I)^{-1} at the start, projected onto
    the tangent space (a cheaper factorization, and the certificate reuses it). Where that
    factor would be nearly dense (shift_invert.krylov_first: an expander) block-Jacobi CG
    first, capped at KRYLOV_CG_CAP steps per Newton system; the factorization only when
    a system needs more (recorded in ``op.paths["polish"]``).
    """
    d, n = op.d, op.n
    X = x_from_rotations(R)
    CX = op.matvec(X)
    use_direct = precondition and op.M > 1 and direct_feasible(op)
    exact = use_direct and newton_direct_feasible(op)
    # Factorization-free first where the factor would be nearly dense (an expander), unless
    # that already stalled on this operator.
    trial = use_direct and krylov_first(op) and op.paths.get("polish") != STALLED
    if trial:
        op.paths["polish"] = "block-jacobi CG"
    cap = KRYLOV_CG_CAP if trial else max_cg
    inverse = None

    def make_prec(X, CX):
        nonlocal inverse
        if exact:
            return NewtonSystem(op, X, CX).step
        inverse = ShiftedInverse(op, multipliers(X, CX, d)[0], SHIFT * lam_max)
        return lambda g: -inverse(g)

    prec = make_prec(X, CX) if use_direct and not trial else None
    refresh_after = 20 if exact else 60
    cg_last = 0
    f = float(np.sum(X * CX))
    scale = lam_max * np.sqrt(n)
    cg_total = 0
    it = 0
    prev = np.inf
    slow = 0  # consecutive Newton steps that did not halve the gradient
    for it in range(max_newton + 1):
        xb = X.reshape(-1, d, d)
        _, g = multipliers(X, CX, d)
        gnorm = float(np.linalg.norm(g))
        # Stop at tolerance, or when Newton repeatedly fails to halve the gradient: the
        # floor set by rounding errors in C X has been reached.
        slow = slow + 1 if gnorm > 0.5 * prev else 0
        if gnorm <= kkt_tol * scale or it == max_newton or slow >= 3:
            break
        prev = gnorm
        if use_direct and not trial and cg_last > refresh_after:
            # The factorization from an earlier point no longer preconditions well: refresh.
            prec = make_prec(X, CX)
        mi = sym(np.einsum("mba,mbc->mac", xb, CX.reshape(-1, d, d)))
        if precondition and op.M > 1 and (trial or not use_direct):
            prec = tangent_block_jacobi(op, xb, mi)  # no factorization (yet)

        def hess(v, xb=xb, mi=mi):
            cv = op.matvec(v).reshape(-1, d, d)
            hv = _tangent_project(xb, cv - v.reshape(-1, d, d) @ mi).reshape(-1, d)
            return _horizontal(xb, hv)

        xi, steps, capped = _newton_cg(hess, prec, xb, g, gnorm / scale, lam_max, cap)
        if trial and capped:
            # Block-Jacobi CG did not converge within its budget: factorize after all (at
            # this point, and for the rest of this operator's polishes).
            trial, cap = False, max_cg
            op.paths["polish"] = STALLED
            prec = make_prec(X, CX)
            cg_total += steps
            xi, steps, _ = _newton_cg(hess, prec, xb, g, gnorm / scale, lam_max, cap)
        cg_total += steps
        cg_last = steps
        # Backtracking line search with the polar retraction.
        slope = float(np.sum(g * xi))
        step = 1.0
        accepted = False
        for _ in range(30):
            xn = project_to_orthogonal(
                (X + step * xi).reshape(-1, d, d), allow_reflections=True
            ).reshape(-1, d)
            cxn = op.matvec(xn)
            fn = float(np.sum(xn * cxn))
            # Armijo decrease; near the optimum the decrease of f drowns in rounding
            # errors, so a step that halves the gradient is accepted too (Newton's regime).
            if fn <= f + 1e-4 * step * min(slope, 0.0) or (
                np.linalg.norm(multipliers(xn, cxn, d)[1]) < 0.5 * gnorm
            ):
                accepted = True
                break
            step *= 0.5
        if not accepted:
            break  # no further decrease at machine precision
        X, CX, f = xn, cxn, fn
    _, g = multipliers(X, CX, d)
    out = rotations_from_x(X, d)
    if not allow_reflections:
        out = project_to_orthogonal(out, allow_reflections=False)
    return out, PolishStats(it, cg_total, float(np.linalg.norm(g)) / scale, f, inverse)


def repolish(
    op,
    R: np.ndarray,
    stats: PolishStats,
    lam_max: float,
    allow_reflections: bool = False,
    kkt_tol: float = KKT_TOL,
    max_passes: int = 4,
) -> tuple[np.ndarray, PolishStats]:
    """Further ``polish`` passes from its output ``(R, stats)`` while it stopped short of a
    KKT point. Returns (R, stats) with the step counts of all passes.

    ``polish`` preconditions every Newton step with the exact Newton system at its start.
    Where the start is not yet in a region of positive curvature (a spectral estimate at
    high noise) that system is indefinite, CG stops after one step, and the steps are too
    weak to halve the gradient: polish gives up with a KKT residual of ~1e-4. A new pass
    factorizes at its own start, nearer the local minimum, where the system is definite
    and Newton converges quadratically. Passes stop at ``kkt_tol``, or when a pass neither
    lowers the cost nor halves the KKT residual (a point that polishing does not improve).
    """
    newton, cg = stats.newton_steps, stats.cg_steps
    for _ in range(max_passes):
        if stats.kkt_residual <= kkt_tol:
            break
        R1, s1 = polish(op, R, lam_max, allow_reflections, kkt_tol=kkt_tol)
        newton, cg = newton + s1.newton_steps, cg + s1.cg_steps
        if s1.objective > stats.objective:
            break  # polish never raises the cost of its start: rounding noise, keep R
        progress = s1.kkt_residual < 0.5 * stats.kkt_residual
        R, stats = R1, s1
        if not progress:
            break
    stats.newton_steps, stats.cg_steps = newton, cg
    return R, stats
