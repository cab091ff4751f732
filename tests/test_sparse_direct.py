"""The sparse direct backends of the solver (MKL PARDISO, SuperLU fallback) and the
large-problem paths they serve: the same rotations and certificates whichever is used."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from data_synth.problems import make_problem
from mvreg.geometry import rotation_angle_deg
from mvreg.solver import RegOperator, certify, pardiso, solve
from mvreg.solver import polish as polish_mod
from mvreg.solver.shift_invert import ShiftedInverse
from mvreg.solver.spectral import lambda_max

needs_pardiso = pytest.mark.skipif(not pardiso.available(), reason="MKL PARDISO not installed")


def _max_angle(a, b):
    return max(rotation_angle_deg(x.T @ y) for x, y in zip(a, b, strict=True))


@pytest.fixture
def no_pardiso():
    with pardiso.disabled():
        yield


@needs_pardiso
def test_pardiso_solves_and_counts_inertia():
    rng = np.random.default_rng(0)
    n = 300
    a = sp.random(n, n, density=0.02, random_state=1)
    a = a + a.T
    shift = np.linspace(-3.0, 30.0, n)  # some negative eigenvalues
    a = (a + sp.diags(shift)).tocsr()
    f = pardiso.PardisoFactor(a)
    b = rng.standard_normal((n, 3))
    x = f.solve(b)
    assert np.linalg.norm(a @ x - b) <= 1e-10 * np.linalg.norm(b)
    x1 = f.solve(b[:, 0])
    assert x1.shape == (n,)
    assert np.allclose(x1, x[:, 0], atol=1e-12)
    w = np.linalg.eigvalsh(a.toarray())
    assert f.perturbed == 0
    assert f.inertia == (int(np.sum(w > 0)), int(np.sum(w < 0)))


def test_superlu_fallback_gives_the_same_solution(no_pardiso):
    problem, _ = make_problem(60, d=3, noise=0.02, seed=11)
    a = solve(problem, method="matrix-free")
    assert a.stats["laplacian"] in ("direct", "amg-cg")
    assert a.certified


@needs_pardiso
def test_pardiso_and_superlu_agree():
    problem, _ = make_problem(60, d=3, noise=0.02, seed=11)
    a = solve(problem, method="matrix-free")
    assert a.stats["laplacian"] == "pardiso"
    with pardiso.disabled():
        b = solve(problem, method="matrix-free")
    assert a.certified and b.certified
    assert _max_angle(a.rotations, b.rotations) < 1e-8
    # PARDISO's inertia proves a lower bound of mu; SuperLU's eigensolver computes mu.
    assert a.certificate.eigen_method == "inertia"
    assert b.certificate.eigen_method == "eigensolver"
    assert 0.25 * b.certificate.min_eigenvalue < a.certificate.min_eigenvalue
    assert a.certificate.min_eigenvalue <= b.certificate.min_eigenvalue + 1e-12


def test_large_problem_newton_preconditioner(monkeypatch):
    """Above the exact-Newton size, polish preconditions with (C + Lambda + sigma I)^{-1}
    and the certificate reuses that factorization: same optimum, certified."""
    problem, _ = make_problem(60, d=3, noise=0.02, seed=11)
    a = solve(problem, method="matrix-free")
    monkeypatch.setattr(polish_mod, "newton_direct_feasible", lambda op: False)
    b = solve(problem, method="matrix-free")
    assert b.certified
    assert _max_angle(a.rotations, b.rotations) < 1e-8
    # b's certificate runs LOBPCG with the polish's factorization (mu itself); a's is the
    # inertia check (a proven lower bound of mu).
    assert b.certificate.eigen_method == "eigensolver"
    assert a.certificate.min_eigenvalue <= b.certificate.min_eigenvalue + 1e-7
    assert a.certificate.min_eigenvalue > 0.25 * b.certificate.min_eigenvalue


def test_matrix_free_certificate_matches_dense_off_optimum():
    """A rotations set far from the optimum: the matrix-free (projected shift-invert)
    certificate finds the same negative eigenvalue as the dense one, and the bordered
    factorization counts C + Lambda's negative eigenvalues (with PARDISO)."""
    problem, _ = make_problem(30, d=3, noise=0.02, seed=4)
    best = solve(problem)
    op = RegOperator(problem)
    lmax = lambda_max(op, True)
    R = best.rotations.copy()
    R[5] = R[5] @ np.diag([-1.0, -1.0, 1.0])  # one patch turned by 180 degrees
    dense = certify(op, R, lmax, dense=True)
    free = certify(op, R, lmax, dense=False)
    assert not dense.certified and not free.certified
    assert dense.min_eigenvalue < -1e-3
    # Off a KKT point span(X) is not exactly invariant under C + Lambda, so the projected
    # shift-invert is approximate there (at the KKT points solve() certifies it is exact).
    assert free.min_eigenvalue == pytest.approx(dense.min_eigenvalue, rel=1e-3)
    if pardiso.available():
        from mvreg.solver.blocks import x_from_rotations
        from mvreg.solver.certificate import multipliers

        X = x_from_rotations(R)
        lam, _ = multipliers(X, op.matvec(X), 3)
        sigma = 1e-4 * lmax
        inv = ShiftedInverse(op, lam, sigma)
        a = op.dense().copy()
        for i in range(op.M):
            a[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += lam[i]
        w = np.linalg.eigvalsh(a)
        assert inv.negative_eigenvalues == int(np.sum(w < -sigma))


@needs_pardiso
@pytest.mark.parametrize(
    ("m", "noise", "graph", "seed"),
    [(60, 0.02, "geometric", 11), (200, 0.05, "random", 3), (150, 0.1, "geometric", 5),
     (300, 0.0, "random", 2), (120, 0.08, "random", 7)],
)  # fmt: skip
def test_inertia_certificate_is_a_lower_bound_of_the_dense_eigenvalue(m, noise, graph, seed):
    """The inertia certificate's min_eigenvalue is a proven lower bound: never above the
    smallest eigenvalue of C + Lambda on the complement that a dense eigendecomposition
    finds, and not far below it (the shift is half of C's spectral gap)."""
    from mvreg.solver.certificate import inertia_shift
    from mvreg.solver.spectral import spectrum

    problem, _ = make_problem(m, d=3, noise=noise, graph=graph, seed=seed)
    res = solve(problem, method="matrix-free", gauge="none")
    op = RegOperator(problem)
    spec = spectrum(op, dense=False)
    tau = inertia_shift(spec.smallest, 3)
    fast = certify(op, res.rotations, spec.largest, dense=False, tau=tau)
    exact = certify(op, res.rotations, spec.largest, dense=True)
    assert res.certified and exact.certified
    assert fast.eigen_method == "inertia" and fast.certified
    assert fast.min_eigenvalue <= exact.min_eigenvalue * (1 + 1e-9)
    assert fast.min_eigenvalue >= 0.2 * exact.min_eigenvalue
    assert fast.min_eigenvalue_full <= exact.min_eigenvalue_full + 1e-12
    assert fast.suboptimality_bound >= 0.0


@needs_pardiso
def test_inertia_certificate_declines_where_curvature_is_negative():
    """Off the optimum (one patch turned 180 deg) the factorization has more than d
    negative pivots: no inertia certificate; the eigensolver finds the negative eigenvalue."""
    from mvreg.solver.certificate import inertia_shift
    from mvreg.solver.spectral import spectrum

    problem, _ = make_problem(80, d=3, noise=0.02, seed=4)
    best = solve(problem)
    op = RegOperator(problem)
    spec = spectrum(op, dense=False)
    R = best.rotations.copy()
    R[5] = R[5] @ np.diag([-1.0, -1.0, 1.0])
    c = certify(op, R, spec.largest, dense=False, tau=inertia_shift(spec.smallest, 3))
    assert not c.certified
    assert c.eigen_method == "eigensolver"
    assert c.min_eigenvalue < -1e-4


@needs_pardiso
def test_laplacian_solves_are_refined_only_when_needed(monkeypatch):
    """The factorized Laplacian solve takes refinement steps only while its backward error
    is above REFINE_BACKWARD_ERROR: none on a clean factorization, and enough to recover
    rounding-level residuals from a solve that is off by 1e-9 (relative)."""
    from mvreg.solver import operator as operator_mod

    problem, _ = make_problem(300, d=3, noise=0.02, graph="random", seed=1)
    S = RegOperator(problem).S
    lap = operator_mod.LaplacianSolver(S, method="pardiso")
    b = np.random.default_rng(0).standard_normal((S.shape[0], 3))
    b -= b.mean(axis=0)
    calls = []
    exact = pardiso.PardisoFactor.solve

    def counted(self, rhs):
        calls.append(1)
        return exact(self, rhs)

    def backward_error(x):
        r = S @ x - b
        return np.max(np.abs(r)) / (abs(S).sum(axis=1).max() * np.max(np.abs(x)))

    monkeypatch.setattr(pardiso.PardisoFactor, "solve", counted)
    x = lap.solve(b)
    assert len(calls) == 1 and backward_error(x) < 1e-14
    rng = np.random.default_rng(1)

    def sloppy(self, rhs):
        calls.append(1)
        return exact(self, rhs) * (1.0 + 1e-9 * rng.standard_normal(rhs.shape))

    monkeypatch.setattr(pardiso.PardisoFactor, "solve", sloppy)
    calls.clear()
    x = lap.solve(b)
    assert len(calls) >= 2 and backward_error(x) < 1e-14
    monkeypatch.setattr(operator_mod, "REFINE_MAX_STEPS", 0)
    assert backward_error(lap.solve(b)) > 1e-11
