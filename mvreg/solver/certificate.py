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

Where a sparse LDL^T factorization with inertia is at hand (PARDISO) the eigensolver is
first replaced by one factorization of C + Lambda - tau I (``_inertia_bound``): exactly d
negative pivots prove mu >= a bound close to tau, with no eigenvector iterations (the
check SE-Sync's successors make with a Cholesky factorization; Papalia et al. 2022). On an
expander-like overlap graph, whose bottom spectrum is clustered, this replaces ~150
shift-invert solves. Where it does not certify, the eigensolver runs as before.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from mvreg.solver import pardiso
from mvreg.solver.blocks import block_apply, sym, x_from_rotations
from mvreg.solver.shift_invert import SHIFT, ShiftedInverse, direct_feasible
from mvreg.solver.spectral import block_jacobi

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
    lower_bound: objective - suboptimality_bound: no rotations reach a lower REG cost (the
        dual bound of Lemma 2 / the C-SDP). Reported whether certified or not, so that an
        uncertified answer still says how far from optimal it can be at most.
    eigen_residual: LOBPCG residual norm of the computed eigenpair (accuracy of mu); 0 for
        ``eigen_method`` "inertia".
    eigen_method: "eigensolver" (min_eigenvalue is the computed eigenvalue), "dense", or
        "inertia": min_eigenvalue is a proven lower bound of mu from the inertia of one
        factorization of C + Lambda - tau I (``_inertia_bound``), not an estimate of it.
    bound_source: where lower_bound (and suboptimality_bound, relative_gap) come from:
        "solution" (lambda_min(C + Lambda) at the solution, above) or "lifted" (the dual
        bound at a lifted point of the Riemannian staircase, staircase.lifted_lower_bound,
        tighter where the relaxation is not tight; only for uncertified solutions).
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
    lower_bound: float = float("nan")
    eigen_method: str = "eigensolver"
    bound_source: str = "solution"

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


def _complement_min_eig(aop, op, lam, q, lam_max, d, seed, maxiter, inverse=None):
    """Smallest eigenvalue of A = C + Lambda on the complement of span(q); residual norm."""
    n = op.n
    rng = np.random.default_rng(seed)
    if inverse is not None:
        # Block LOBPCG on the complement, preconditioned by a (C + Lambda' + sigma I)^{-1}
        # factorized at a nearby point (the Newton polish's, on large problems).
        return _lobpcg_min_eig(aop, inverse, q, lam_max, rng, n)
    if direct_feasible(op):
        # Shift-invert Lanczos on the complement of span(q) with the exact
        # (A + sigma I)^{-1} from one sparse factorization, projected: OPinv = P (A+sI)^{-1} P
        # has the eigenvalues 1 / (mu + sigma) on the complement and 0 on span(q), so only
        # the complement's smallest eigenvalues are sought.
        # The shift: SHIFT lambda_max, raised tenfold while the factorization's inertia says
        # A + sigma I is indefinite (then eigenvalues below -sigma exist, which shift-invert
        # near -sigma could miss). Without inertia (SuperLU) a LOBPCG guard follows instead.
        sigma = SHIFT * lam_max
        inv = ShiftedInverse(op, lam, sigma)
        neg0 = inv.negative_eigenvalues
        while inv.negative_eigenvalues and sigma < 1e3 * lam_max:
            sigma *= 10.0
            inv = ShiftedInverse(op, lam, sigma)

        def project(r):
            return r - q @ (q.T @ r)

        def pinv(r):
            r2 = r[:, None] if r.ndim == 1 else r
            y = project(inv(project(r2)))
            return y[:, 0] if r.ndim == 1 else y

        opinv = spla.LinearOperator((n, n), matvec=pinv, matmat=pinv, dtype=np.float64)
        k = min(2, n - d - 1)
        v0 = project(rng.standard_normal((n, 1)))[:, 0]
        w, v = spla.eigsh(aop, k=k, sigma=-sigma, OPinv=opinv, which="LM", tol=1e-10, v0=v0)
        mu = float(np.min(w))
        res = float(np.linalg.norm(aop.matmat(v) - v * w))
        if neg0 is not None and neg0 > d:
            # More than d eigenvalues of A below -SHIFT lambda_max: since q^T A q = 0, by
            # interlacing at least one lies below it on the complement too.
            mu = min(mu, -SHIFT * lam_max)
        if inv.negative_eigenvalues == 0:
            # A + sigma I is positive definite: no eigenvalue lies below -sigma, where
            # shift-invert could miss it.
            return mu, res
        # Guard against eigenvalues far below -sigma, which shift-invert would not see:
        # a short LOBPCG on the complement, preconditioned by the same inverse.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            w2, _ = spla.lobpcg(
                aop, rng.standard_normal((n, 2)), Y=q, M=opinv, largest=False, maxiter=20
            )
        return min(mu, float(np.min(w2))), res
    # No factorization affordable: LOBPCG on the complement, preconditioned by the inverse
    # diagonal blocks of C0 (without it, M = 3,000 random graph: residual 9e-5 lambda_max
    # after 400 steps, and a Ritz value above lambda_min; with it 1e-6 within 334 steps).
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w, _, hist = spla.lobpcg(
            aop,
            rng.standard_normal((n, min(3, n - d))),
            Y=q,
            M=block_jacobi(op),
            largest=False,
            tol=1e-6 * lam_max,
            maxiter=maxiter,
            retResidualNormsHistory=True,
        )
    return float(np.min(w)), float(np.min(hist[-1])) if len(hist) else float("nan")


def _lobpcg_min_eig(aop, inverse, q, lam_max, rng, n, block=4, maxiter=60):
    opinv = spla.LinearOperator((n, n), matvec=inverse, matmat=inverse, dtype=np.float64)
    x0 = rng.standard_normal((n, block))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w, v = spla.lobpcg(
            aop, x0, Y=q, M=opinv, largest=False, tol=1e-9 * lam_max, maxiter=maxiter
        )
    i = int(np.argmin(w))
    vi = v[:, i : i + 1]
    res = float(np.linalg.norm(aop.matmat(vi) - w[i] * vi))
    return float(w[i]), res


def inertia_shift(smallest: np.ndarray, d: int) -> float | None:
    """The shift tau for ``_inertia_bound`` from the d+1 smallest eigenvalues of C:
    half the gap lambda_{d+1}(C) - lambda_d(C). At an optimum C + Lambda ~ C - lambda_bar I
    on the complement of the solution, so mu is near that gap (random graph, M = 1,000,
    noise 4%: gap 1.25e-3, mu 1.28e-3; geometric, M = 10,000: 1.8e-4 and 1.9e-4, relative
    to lambda_max). None when there is no gap."""
    if smallest is None or len(smallest) <= d:
        return None
    gap = float(smallest[d] - smallest[d - 1])
    return 0.5 * gap if gap > 0 else None


def _inertia_bound(aop, op, lam, q, tau: float, d: int):
    """(mu_lb, lam_min_full_lb): proven lower bounds of mu (the smallest eigenvalue of
    A = C + Lambda on the complement of span(q)) and of lambda_min(A), from the inertia of
    one LDL^T factorization of A - tau I; None when it does not apply.

    If A - tau I has exactly d negative eigenvalues (the factor's negative pivots, Sylvester
    and Haynsworth: shift_invert.ShiftedInverse), A has exactly d eigenvalues below tau,
    with eigenspace U. span(q) has Ritz values H = q^T A q in [h_lo, h_hi] (~0 at a KKT
    point) and residual R = A q - q H. When r = ||R||_2 < delta = tau - h_hi:
    - Kahan's theorem puts d eigenvalues of A within r of the Ritz values; they are below
      tau, so they are U's: lambda_min(A) >= h_lo - r;
    - the Davis-Kahan sin-theta theorem bounds the angle between span(q) and U:
      sin <= s = r / delta. A unit w orthogonal to q has ||P_U w|| <= s, hence
      w^T A w >= (1 - s^2) tau + s^2 (h_lo - r) =: mu_lb;
    - in the basis [q, complement] A = [[H, E^T], [E, B]] with ||E|| <= r and B >= mu_lb,
      so lambda_min(A) >= the smaller eigenvalue of [[h_lo, r], [r, mu_lb]].
    """
    if tau is None or not tau > 0 or not pardiso.available():
        return None
    neg = ShiftedInverse(op, lam, -tau).negative_eigenvalues
    if neg != d:
        return None  # not known (perturbed pivots, SuperLU) or mu < tau: the eigensolver
    aq = aop.matmat(q)
    h = q.T @ aq
    h = 0.5 * (h + h.T)
    r = float(np.linalg.norm(aq - q @ h, 2))
    hw = np.linalg.eigvalsh(h)
    delta = tau - float(hw[-1])
    if not r < delta:
        return None
    s2 = (r / delta) ** 2
    low = float(hw[0]) - r
    mu_lb = (1.0 - s2) * tau + s2 * min(low, tau)
    a, b = float(hw[0]), mu_lb
    two_by_two = 0.5 * ((a + b) - np.sqrt((b - a) ** 2 + 4.0 * r * r))
    return mu_lb, min(0.0, max(low, two_by_two))


def certify(
    op,
    R: np.ndarray,
    lam_max: float,
    dense: bool,
    gap_tol: float = DEFAULT_GAP_TOL,
    seed: int = 0,
    maxiter: int = 400,
    inverse=None,
    tau: float | None = None,
) -> Certificate:
    """Certificate for rotations R (M, d, d) of the normalized problem in ``op``.

    ``inverse``: an approximate (C + Lambda + sigma I)^{-1} from a nearby point (the Newton
    polish's preconditioner on large problems) to precondition the eigensolver with, instead
    of factorizing anew.
    ``tau``: the shift of the inertia check (``inertia_shift``, in C's units); tried first
    where a sparse factorization with inertia is affordable and no ``inverse`` is given.
    """
    d, n = op.d, op.n
    X = x_from_rotations(R)
    CX = op.matvec(X)
    f_norm = float(np.sum(X * CX))
    lam, grad = multipliers(X, CX, d)
    e_fro = float(np.linalg.norm(grad))
    kkt = e_fro / (lam_max * np.sqrt(n))
    q, _ = np.linalg.qr(X)
    s2 = op.norm.scale**2

    def outcome(mu, lam_min_full, eig_res, method):
        bound_norm = max(0.0, -lam_min_full) * n
        objective, bound = f_norm * s2, bound_norm * s2
        if objective > 0:
            rel = bound / max(objective, 1e-300)
        else:
            rel = 0.0 if bound == 0 else np.inf
        # Absolute floor: clean data has objective ~0; compare with lambda_max's scale too.
        certified = bool(
            mu >= -EIG_TOL * lam_max
            and (rel <= gap_tol or bound_norm <= gap_tol * 1e-6 * lam_max * n)
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
            lower_bound=objective - bound,
            eigen_method=method,
        )

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
        return outcome(mu, _full_bound(mu, grad, e_fro), 0.0, "dense")

    def apply(v):
        return op.matvec(v) + block_apply(lam, v)

    aop = spla.LinearOperator((n, n), matvec=apply, matmat=apply, dtype=np.float64)
    if inverse is None and tau is not None and direct_feasible(op):
        fast = _inertia_bound(aop, op, lam, q, tau, d)
        if fast is not None:
            cert = outcome(fast[0], fast[1], 0.0, "inertia")
            if cert.certified:
                return cert
    mu, eig_res = _complement_min_eig(aop, op, lam, q, lam_max, d, seed, maxiter, inverse)
    return outcome(mu, _full_bound(mu, grad, e_fro), eig_res, "eigensolver")


def _full_bound(mu: float, grad: np.ndarray, e_fro: float) -> float:
    """A lower bound on lambda_min(C + Lambda) from mu and the KKT residual (module doc)."""
    e2 = float(np.linalg.norm(grad, 2)) if e_fro > 0 else 0.0
    return min(0.0, 0.5 * (mu - np.sqrt(mu * mu + 4.0 * e2 * e2))) if mu > 0 else mu
