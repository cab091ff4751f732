"""Escape from a stationary point that the certificate rejects: one Riemannian staircase step
(Boumal's staircase as in SE-Sync and Shonan averaging; DESIGN.md section 4).

At rotations R with multipliers Lambda (certificate.multipliers), a negative eigenvalue
mu < 0 of S = C + Lambda on the complement of span(X) (X = O^T) has an eigenvector v with
v^T S v = mu < 0. In the lifted problem

    min Tr(Y^T C Y)  over Y (n, d + 1) with every block Y_i (d x (d + 1)) having orthonormal rows

(G = Y Y^T is still feasible for REG-SDP), Y = [X, 0] is a stationary point and [0, v] a
tangent direction of negative curvature mu: the cost falls along it. ``escape`` steps
along it (backtracking on the lifted cost), descends in the lifted space by Riemannian
gradient descent with Barzilai-Borwein steps (``lifted_descent``), and rounds back to rank
d (the top d singular directions of Y, blockwise projected onto SO(d) / O(d)). The caller
polishes and certifies the result.

The descent was the generalized power method (Y_i <- polar factor of ((lambda_max I - C)
Y)_i, paper 001 Algorithm 1 with d x (d + 1) blocks): monotone, but its step is
1 / lambda_max, and where lambda_{d+1} / lambda_max is ~1e-4 (large problems, high noise)
it moves a negligible distance per step. It stopped after one step on the random graph at
M = 10,000 and 8% noise (a decrease below its relative tolerance), and ran out of its 300
steps elsewhere (M = 300 at 20% noise: uncertified after 40 s; the Barzilai-Borwein
descent certifies a 2.7% cheaper optimum in 1.9 s; docs/design/solver.md).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse.linalg as spla

from mvreg.solver.blocks import block_apply, round_to_rotations, x_from_rotations
from mvreg.solver.certificate import multipliers


@dataclass
class EscapeStats:
    min_eigenvalue: float  # mu / lambda_max(C) at the start (< 0 when an escape was taken)
    step: float  # the accepted step along the lifted direction
    iterations: int  # steps of the lifted descent
    lifted_cost: float  # Tr(Y^T C Y) of the lifted point (normalized units)
    start_cost: float  # Tr(X^T C X) at the start (normalized units)
    lifted: np.ndarray | None = field(default=None, repr=False)  # the lifted point Y (n, d+1)


DENSE_MAX = 600  # below this size the eigenproblem is solved densely


def _polar_rows(Y: np.ndarray, d: int) -> np.ndarray:
    """Each d x p block of Y (n, p) replaced by the nearest block with orthonormal rows."""
    p = Y.shape[1]
    u, _, vt = np.linalg.svd(Y.reshape(-1, d, p), full_matrices=False)
    return (u @ vt).reshape(-1, p)


def most_negative_direction(op, X: np.ndarray, lam: np.ndarray, lam_max: float, seed: int):
    """(mu, v): the smallest eigenvalue of C + Lambda on the complement of span(X), unit v (n,)."""
    n = op.n
    q, _ = np.linalg.qr(X)

    def apply(v):
        return op.matvec(v) + block_apply(lam, v)

    if n <= DENSE_MAX:  # lobpcg solves small problems densely, where it takes no constraint
        A = apply(np.eye(n))
        P = np.eye(n) - q @ q.T
        shift = 2.0 * (abs(lam_max) + float(np.max(np.abs(A)))) + 1.0  # span(X) to the top
        w, V = np.linalg.eigh(P @ ((A + A.T) / 2) @ P + shift * (q @ q.T))
    else:
        aop = spla.LinearOperator((n, n), matvec=apply, matmat=apply, dtype=np.float64)
        x0 = np.random.default_rng(seed).standard_normal((n, 3))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            w, V = spla.lobpcg(aop, x0, Y=q, largest=False, tol=1e-6 * lam_max, maxiter=200)
    i = int(np.argmin(w))
    v = V[:, i] - q @ (q.T @ V[:, i])
    return float(w[i]), v / np.linalg.norm(v)


def _row_multipliers(Y: np.ndarray, CY: np.ndarray, d: int) -> np.ndarray:
    """(M, d, d) blocks sym((C Y)_i Y_i^T) for Y (n, p) with orthonormal block rows: minus
    the multipliers Lambda(Y) of the lifted problem (for p = d, certificate.multipliers)."""
    p = Y.shape[1]
    m = CY.reshape(-1, d, p) @ Y.reshape(-1, d, p).transpose(0, 2, 1)
    return 0.5 * (m + m.transpose(0, 2, 1))


def _riemannian_gradient(Y: np.ndarray, CY: np.ndarray, d: int) -> np.ndarray:
    """Gradient of Tr(Y^T C Y) projected onto the tangent space of blocks with orthonormal
    rows: G_i - sym(G_i Y_i^T) Y_i with G = 2 C Y."""
    n, p = Y.shape
    sym_b = _row_multipliers(Y, CY, d)
    return (2.0 * (CY.reshape(-1, d, p) - sym_b @ Y.reshape(-1, d, p))).reshape(n, p)


# Nonmonotone line search: the cost must fall below the largest of the last NONMONOTONE
# costs (Grippo, Lampariello and Lucidi), which lets Barzilai-Borwein steps through valleys.
NONMONOTONE = 10
# The descent stops when its best cost has fallen by less than tol (relative) over this many
# steps. Its point also gives a lower bound (lifted_lower_bound), tight only near the
# lifted problem's optimum, hence the small tolerance: random graph, M = 10,000, 8% noise,
# the cost falls by ~1e-9 (relative) per 50 steps near the end, while the gradient still
# falls tenfold (docs/design/solver.md).
STALL_WINDOW = 50
# The longest step (times 1 / lambda_max) taken along negative curvature.
MAX_STEP = 1e4


def lifted_descent(op, Y: np.ndarray, d: int, lam_max: float, max_iter: int, tol: float):
    """Riemannian gradient descent on the blocks with orthonormal rows from Y (n, p):
    Barzilai-Borwein step sizes (BB1 and BB2 alternately), nonmonotone Armijo backtracking,
    polar retraction. Returns (Y, cost, steps). Stops after ``max_iter`` steps, when the
    best cost has fallen by less than ``tol`` (relative) over ``STALL_WINDOW`` steps, or at
    a gradient of 1e-9 lambda_max sqrt(n)."""
    n = Y.shape[0]
    cy = op.matvec(Y)
    f = float(np.sum(Y * cy))
    g = _riemannian_gradient(Y, cy, d)
    costs, bests = [f], [f]
    y_best, f_best = Y, f
    alpha = 1.0 / (2.0 * lam_max)  # the power method's step for the first one
    g_floor = 1e-9 * lam_max * np.sqrt(n)
    it = 0
    while it < max_iter and float(np.linalg.norm(g)) > g_floor:
        it += 1
        f_ref, gg = max(costs[-NONMONOTONE:]), float(np.sum(g * g))
        a = alpha
        for _ in range(40):
            y_new = _polar_rows(Y - a * g, d)
            cy_new = op.matvec(y_new)
            f_new = float(np.sum(y_new * cy_new))
            if f_new <= f_ref - 1e-4 * a * gg:
                break
            a *= 0.5
        else:
            break  # no decrease at any step length: rounding level
        g_new = _riemannian_gradient(y_new, cy_new, d)
        s, yv = y_new - Y, g_new - g
        sy = float(np.sum(s * yv))
        if sy > 0:
            alpha = float(np.sum(s * s)) / sy if it % 2 else sy / float(np.sum(yv * yv))
        else:
            # Negative curvature along the last step (escaping the saddle): no BB step
            # exists; a longer step than the one accepted, the line search guarding it.
            alpha = min(4.0 * a, MAX_STEP / lam_max)
        Y, cy, f, g = y_new, cy_new, f_new, g_new
        costs.append(f)
        if f <= f_best:
            y_best, f_best = Y, f
        bests.append(f_best)
        if it >= STALL_WINDOW and bests[-STALL_WINDOW - 1] - f_best <= tol * abs(f_best):
            break
    # A nonmonotone run can end above the best point it passed: return that one.
    return y_best, f_best, it


def escape(
    op,
    R: np.ndarray,
    lam_max: float,
    allow_reflections: bool = False,
    seed: int = 0,
    max_iter: int = 1000,
    tol: float = 1e-10,
) -> tuple[np.ndarray | None, EscapeStats]:
    """One staircase step from rotations R (M, d, d). Returns (rotations or None, stats):
    None when C + Lambda has no negative eigenvalue on the complement (nothing to escape)."""
    d, m = op.d, op.M
    X = x_from_rotations(R)
    CX = op.matvec(X)
    f0 = float(np.sum(X * CX))
    lam, _ = multipliers(X, CX, d)
    mu, v = most_negative_direction(op, X, lam, lam_max, seed)
    stats = EscapeStats(mu / lam_max, 0.0, 0, f0, f0)
    if mu >= 0:
        return None, stats
    # Tangent direction [0, sqrt(M) v]: blocks of norm ~1; backtrack until the cost falls.
    direction = math.sqrt(m) * v[:, None]
    step, Y, f = 1.0, None, f0
    for _ in range(30):
        cand = _polar_rows(np.hstack([X, step * direction]), d)
        fc = float(np.sum(cand * op.matvec(cand)))
        if fc < f0:
            Y, f = cand, fc
            break
        step *= 0.5
    if Y is None:
        return None, stats
    Y, f, it = lifted_descent(op, Y, d, lam_max, max_iter, tol)
    stats.step, stats.iterations, stats.lifted_cost, stats.lifted = step, it, f, Y
    # Round to rank d: the top-d singular directions of Y, then blockwise projection.
    u, s, _ = np.linalg.svd(Y, full_matrices=False)
    return round_to_rotations(u[:, :d] * s[:d], d, allow_reflections), stats


def lifted_lower_bound(op, Y: np.ndarray, lam_max: float, seed: int = 0, maxiter: int = 400):
    """A lower bound on the optimum of REG from a lifted point Y (n, p) (normalized units):
    (bound, lambda_min estimate, its residual).

    With Lambda(Y)_i = -sym((C Y)_i Y_i^T), -sum tr Lambda_i = Tr(Y^T C Y) = f(Y), and every
    feasible G (G_ii = I, G >= 0) has Tr(C G) = Tr((C + Lambda) G) - sum tr Lambda_i
    >= lambda_min(C + Lambda) n + f(Y): the dual bound of paper 000 Lemma 2 at Lambda(Y). It
    bounds the SDP relaxation, hence REG, from below; at a lifted point near the
    relaxation's optimum lambda_min is ~0 and the bound is tight even where no rank-d point
    is certified (the relaxation is not tight there). lambda_min is LOBPCG's smallest Ritz
    value (block-Jacobi preconditioned, started from Y's columns) minus its residual norm:
    an estimate, as reliable as the eigensolver's convergence.
    """
    from mvreg.solver.blocks import block_apply
    from mvreg.solver.spectral import block_jacobi

    d, n = op.d, op.n
    cy = op.matvec(Y)
    lam = -_row_multipliers(Y, cy, d)
    f_y = float(np.sum(Y * cy))

    def apply(v):
        return op.matvec(v) + block_apply(lam, v)

    if n <= DENSE_MAX:
        a = apply(np.eye(n))
        lam_min = float(np.linalg.eigvalsh(0.5 * (a + a.T))[0])
        return f_y + min(0.0, lam_min) * n, lam_min, 0.0
    aop = spla.LinearOperator((n, n), matvec=apply, matmat=apply, dtype=np.float64)
    rng = np.random.default_rng(seed)
    x0 = np.hstack([np.linalg.qr(Y)[0], rng.standard_normal((n, 2))])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w, v = spla.lobpcg(
            aop, x0, M=block_jacobi(op), largest=False, tol=1e-9 * lam_max, maxiter=maxiter
        )
    i = int(np.argmin(w))
    res = float(np.linalg.norm(aop.matmat(v[:, i : i + 1]) - w[i] * v[:, i : i + 1]))
    lam_min = float(w[i])
    return f_y + min(0.0, lam_min - res) * n, lam_min, res
