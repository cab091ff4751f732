"""Global-optimality certificate (paper 000 Lemma 1, Lemma 2, Prop. 2; DESIGN.md section 4).

For rotations R (X = O^T, X_i = R_i^T) let Lambda_i = -sym([C G]_ii) = -X_i M_i X_i^T with
M_i = sym(X_i^T (C X)_i). Then Tr((C + Lambda) G) = 0 for every feasible G with G_ii = I,
hence for every feasible G:  Tr(C G) - Tr(C G*) = Tr((C + Lambda) G) >= lambda_min(C + Lambda) M d.
If C + Lambda is PSD the solution is a global optimum of REG-SDP (and of O-REG / REG).

We compute mu = the smallest eigenvalue of C + Lambda on the orthogonal complement of the
columns of X (LOBPCG with constraints), and the KKT residual E = ||(C + Lambda) X||. Since
X^T (C + Lambda) X = 0 exactly, lambda_min(C + Lambda) >= (mu - sqrt(mu^2 + 4 ||E||_2^2)) / 2,
which gives a rigorous bound on the suboptimality even for a slightly inexact stationary
point. All eigenvalues are reported relative to lambda_max(C) (dimensionless).
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from mvreg.solver.blocks import block_apply, sym, x_from_rotations
from mvreg.solver.shift_invert import ShiftedInverse, direct_feasible

# certified iff the relative suboptimality bound is below this (and mu >= -EIG_TOL).
DEFAULT_GAP_TOL = 1e-6
EIG_TOL = 1e-9


@dataclass
class Certificate:
    """Outcome of the optimality check of one solution.

    certified: the solution is a global optimum up to ``suboptimality_bound``.
    objective: REG cost sum w ||z - R x - t||^2 at the solution, in the problem's units.
    kkt_residual: ||(C + Lambda) X||_F / (lambda_max(C) sqrt(Md)) (0 at a KKT point, Lemma 1).
    min_eigenvalue: smallest eigenvalue of C + Lambda on the complement of the solution,
        divided by lambda_max(C) (> 0: strict, unique optimum up to gauge).
    min_eigenvalue_full: a lower bound on lambda_min(C + Lambda) / lambda_max(C) over the
        whole space (from min_eigenvalue and the KKT residual).
    suboptimality_bound: f(solution) - f(optimum) <= this, in the problem's units.
    relative_gap: suboptimality_bound / max(objective, tiny).
    eigen_residual: LOBPCG residual norm of the computed eigenpair (accuracy of mu).
    """

    certified: bool
    objective: float
    kkt_residual: float
    min_eigenvalue: float
    min_eigenvalue_full: float
    suboptimality_bound: float
    relative_gap: float
    eigen_residual: float
    tolerance: float

    def to_dict(self) -> dict:
        return {k: (bool(v) if isinstance(v, np.bool_) else v) for k, v in asdict(self).items()}


def multipliers(X: np.ndarray, CX: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    """Lambda blocks (M, d, d) and the Riemannian gradient (n, d) = (C + Lambda) X."""
    xb = X.reshape(-1, d, d)
    cxb = CX.reshape(-1, d, d)
    mi = sym(np.einsum("mba,mbc->mac", xb, cxb))  # sym(X_i^T (CX)_i)
    lam = -np.einsum("mab,mbc,mdc->mad", xb, mi, xb)  # -X_i M_i X_i^T
    grad = (cxb - xb @ mi).reshape(-1, d)  # (C + Lambda) X
    return lam, grad


def _complement_min_eig(aop, op, lam, q, lam_max, d, seed, maxiter):
    """Smallest eigenvalue of A = C + Lambda on the complement of span(q); residual norm."""
    n = op.n
    rng = np.random.default_rng(seed)
    if direct_feasible(op):
        # Shift-invert Lanczos with the exact (A + sigma I)^{-1} (one sparse LU): the d null
        # vectors of A and the next eigenvalues, accurately, in a few iterations.
        sigma = 1e-4 * lam_max
        inv = ShiftedInverse(op, lam, sigma)
        opinv = spla.LinearOperator((n, n), matvec=inv, matmat=inv, dtype=np.float64)
        k = min(d + 2, n - 1)
        w, v = spla.eigsh(
            aop, k=k, sigma=-sigma, OPinv=opinv, which="LM", tol=1e-10, v0=rng.standard_normal(n)
        )
        # Drop the d eigenvectors lying in span(q) (the solution's own null space).
        inside = np.linalg.norm(q.T @ v, axis=0)
        keep = np.argsort(inside)[: k - d]
        mu = float(np.min(w[keep]))
        res = float(np.linalg.norm(aop.matmat(v[:, keep]) - v[:, keep] * w[keep]))
        # Guard against eigenvalues far below -sigma, which shift-invert would not see:
        # a short LOBPCG on the complement, preconditioned by the same inverse.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            w2, _ = spla.lobpcg(
                aop, rng.standard_normal((n, 2)), Y=q, M=opinv, largest=False, maxiter=20
            )
        return min(mu, float(np.min(w2))), res
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w, _, hist = spla.lobpcg(
            aop,
            rng.standard_normal((n, min(3, n - d))),
            Y=q,
            largest=False,
            tol=1e-6 * lam_max,
            maxiter=maxiter,
            retResidualNormsHistory=True,
        )
    return float(np.min(w)), float(np.min(hist[-1])) if len(hist) else float("nan")


def certify(
    op,
    R: np.ndarray,
    lam_max: float,
    dense: bool,
    gap_tol: float = DEFAULT_GAP_TOL,
    seed: int = 0,
    maxiter: int = 400,
) -> Certificate:
    """Certificate for rotations R (M, d, d) of the normalized problem in ``op``."""
    d, n = op.d, op.n
    X = x_from_rotations(R)
    CX = op.matvec(X)
    f_norm = float(np.sum(X * CX))
    lam, grad = multipliers(X, CX, d)
    e_fro = float(np.linalg.norm(grad))
    kkt = e_fro / (lam_max * np.sqrt(n))
    q, _ = np.linalg.qr(X)
    if dense or n <= 60:  # tiny problems: iterative eigensolvers need n >> block size
        a = op.dense().copy()
        for i in range(op.M):
            a[i * d : (i + 1) * d, i * d : (i + 1) * d] += lam[i]
        # Restrict to the complement of span(X): P A P with P = I - q q^T, then drop
        # the d zero eigenvalues that belong to span(X).
        pa = a - q @ (q.T @ a)
        pap = pa - (pa @ q) @ q.T
        pap = 0.5 * (pap + pap.T)
        # Shift span(X) up so it does not mask the complement's smallest eigenvalue.
        pap += q @ q.T * (2.0 * lam_max)
        mu = float(sla.eigh(pap, eigvals_only=True, subset_by_index=[0, 0])[0])
        eig_res = 0.0
    else:

        def apply(v):
            return op.matvec(v) + block_apply(lam, v)

        aop = spla.LinearOperator((n, n), matvec=apply, matmat=apply, dtype=np.float64)
        mu, eig_res = _complement_min_eig(aop, op, lam, q, lam_max, d, seed, maxiter)
    e2 = float(np.linalg.norm(grad, 2)) if e_fro > 0 else 0.0
    lam_min_full = min(0.0, 0.5 * (mu - np.sqrt(mu * mu + 4.0 * e2 * e2))) if mu > 0 else mu
    s2 = op.norm.scale**2
    bound_norm = max(0.0, -lam_min_full) * n
    objective = f_norm * s2
    bound = bound_norm * s2
    rel = bound / max(objective, 1e-300) if objective > 0 else (0.0 if bound == 0 else np.inf)
    # Absolute floor: clean data has objective ~0; compare with lambda_max's scale too.
    certified = bool(
        mu >= -EIG_TOL * lam_max and (rel <= gap_tol or bound_norm <= gap_tol * 1e-6 * lam_max * n)
    )
    return Certificate(
        certified=certified,
        objective=objective,
        kkt_residual=kkt,
        min_eigenvalue=mu / lam_max,
        min_eigenvalue_full=lam_min_full / lam_max,
        suboptimality_bound=bound,
        relative_gap=float(rel),
        eigen_residual=eig_res,
        tolerance=gap_tol,
    )
