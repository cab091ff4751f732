"""Factorization-free paths where the factor would be nearly dense (issue 15, random graph):
the fill test, the Jacobi-PCG Laplacian and its fallback, and the Newton polish by
block-Jacobi CG (with its fallback to the factorization)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from data_synth.problems import make_problem
from mvreg.metrics import rotation_errors_deg
from mvreg.solver import RegOperator, pardiso, polish, solve
from mvreg.solver.krylov import dense_factor, fill_density, laplacian_pcg
from mvreg.solver.operator import LaplacianSolver

needs_pardiso = pytest.mark.skipif(not pardiso.available(), reason="MKL PARDISO not loadable")


def test_fill_density():
    assert fill_density(55, 10) == pytest.approx(1.0)
    assert dense_factor(20, 10, 1e9) and not dense_factor(5, 10, 1e9)
    assert not dense_factor(20, 10, 1e6)  # a cheap factorization: factorize


def test_laplacian_pcg_solves_a_random_graph_laplacian_to_rounding():
    problem, _ = make_problem(2000, d=3, noise=0.01, graph="random", seed=1)
    op = RegOperator(problem, laplacian="direct")
    b = op.B.T @ np.random.default_rng(0).standard_normal((op.n, 3))
    ref = op.lap.solve(b)
    x, its, ok = laplacian_pcg(op.S, b)
    assert ok and its < 80  # an expander: a few dozen steps to 1e-15
    assert np.linalg.norm(x - ref) <= 1e-12 * np.linalg.norm(ref)
    assert np.abs(x.sum(axis=0)).max() < 1e-9 * np.abs(x).max()


@needs_pardiso
def test_laplacian_pcg_falls_back_to_the_factor_where_it_does_not_converge():
    m = 3000  # a path graph: spectral gap ~ 1/M^2, CG needs ~M steps
    ones = np.ones(m - 1)
    S = sp.diags([-ones, np.r_[1.0, 2.0 * ones[1:], 1.0], -ones], [-1, 0, 1], format="csr")
    b = np.random.default_rng(0).standard_normal((m, 2))
    b -= b.mean(axis=0)
    ref = LaplacianSolver(S, "pardiso").solve(b)
    lap = LaplacianSolver(S, "pcg")
    x = lap.solve(b)
    assert lap.method == "pardiso" and lap.cg_iterations > 0
    np.testing.assert_allclose(x, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


@needs_pardiso
def test_random_graph_polish_without_factorization_certified():
    """M = 500 (matrix-free): the bordered factor is nearly dense, so the polish runs
    block-Jacobi CG without factorizing; the result is certified and as accurate."""
    problem, truth = make_problem(500, d=3, degree=6, nodes_per_pair=20, noise=0.04,
                                  graph="random", seed=0)  # fmt: skip
    res = solve(problem, method="matrix-free")
    assert res.stats["factor_forecast"]["dense"] and res.stats["factor_forecast"]["fill"] > 0.1
    assert res.stats["paths"]["polish"] == "block-jacobi CG"
    assert res.certified and res.certificate.min_eigenvalue > 1e-4
    err = rotation_errors_deg(res.rotations, truth.rotations)
    assert np.median(err) < 0.6 and err.max() < 4.0


@needs_pardiso
def test_geometric_graph_keeps_the_factorization():
    problem, _ = make_problem(1000, d=3, noise=0.04, graph="geometric", seed=0)
    res = solve(problem)
    assert not res.stats["factor_forecast"]["dense"]
    assert "polish" not in res.stats["paths"] and res.stats["laplacian"] == "pardiso"
    assert res.certified


@needs_pardiso
def test_polish_falls_back_to_the_factorization_when_cg_stalls(monkeypatch):
    problem, _ = make_problem(500, d=3, degree=6, nodes_per_pair=20, noise=0.04,
                              graph="random", seed=0)  # fmt: skip
    ref = solve(problem, method="matrix-free")
    monkeypatch.setattr(polish, "KRYLOV_CG_CAP", 2)
    res = solve(problem, method="matrix-free")
    assert res.stats["paths"]["polish"] == polish.STALLED
    assert res.certified
    assert rotation_errors_deg(res.rotations, ref.rotations).max() < 1e-6
