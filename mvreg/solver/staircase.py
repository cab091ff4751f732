"""Escape from a stationary point that the certificate rejects: one Riemannian staircase step
(Boumal's staircase as in SE-Sync and Shonan averaging; DESIGN.md section 4).

At rotations R with multipliers Lambda (certificate.multipliers), a negative eigenvalue
mu < 0 of S = C + Lambda on the complement of span(X) (X = O^T) has an eigenvector v with
v^T S v = mu < 0. In the lifted problem

    min Tr(Y^T C Y)  over Y (n, d + 1) with every block Y_i (d x (d + 1)) having orthonormal rows

(G = Y Y^T is still feasible for REG-SDP), Y = [X, 0] is a stationary point and [0, v] a
tangent direction of negative curvature mu: the cost falls along it. ``escape`` steps
along it (backtracking on the lifted cost), descends in the lifted space with the
generalized power method (Y_i <- polar factor of ((alpha I - C) Y)_i, alpha >= lambda_max(C):
monotone, paper 001 Algorithm 1 with d x (d + 1) blocks), and rounds back to rank d (the
top d singular directions of Y, blockwise projected onto SO(d) / O(d)). The caller
polishes and certifies the result.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse.linalg as spla

from mvreg.solver.blocks import block_apply, round_to_rotations, x_from_rotations
from mvreg.solver.certificate import multipliers


@dataclass
class EscapeStats:
    min_eigenvalue: float  # mu / lambda_max(C) at the start (< 0 when an escape was taken)
    step: float  # the accepted step along the lifted direction
    iterations: int  # lifted power iterations
    lifted_cost: float  # Tr(Y^T C Y) of the lifted point (normalized units)
    start_cost: float  # Tr(X^T C X) at the start (normalized units)


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


def escape(
    op,
    R: np.ndarray,
    lam_max: float,
    allow_reflections: bool = False,
    seed: int = 0,
    max_iter: int = 300,
    tol: float = 1e-7,
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
    cy = op.matvec(Y)
    it = 0
    while it < max_iter:
        it += 1
        Y = _polar_rows(lam_max * Y - cy, d)
        cy = op.matvec(Y)
        fn = float(np.sum(Y * cy))
        done = f - fn <= tol * abs(f)
        f = fn
        if done:
            break
    stats.step, stats.iterations, stats.lifted_cost = step, it, f
    # Round to rank d: the top-d singular directions of Y, then blockwise projection.
    u, s, _ = np.linalg.svd(Y, full_matrices=False)
    return round_to_rotations(u[:, :d] * s[:d], d, allow_reflections), stats
