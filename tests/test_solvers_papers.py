"""The solvers of the papers (issue 5): c-admm, gpm, balm (and spectral / reg-admm)."""

from __future__ import annotations

import numpy as np
import pytest

from data_synth.problems import make_problem
from mvreg.errors import ConfigError
from mvreg.geometry import random_rotations, rotation_angle_deg
from mvreg.metrics import rotation_errors_deg
from mvreg.solver import PatchProblem, solve
from mvreg.solver import c_admm as c_admm_module
from mvreg.solver.base import SOLVERS

PAPER_SOLVERS = ("gpm", "balm", "c-admm")


def _perturbed(truth_rotations, deg: float, seed: int) -> np.ndarray:
    """Truth with every rotation moved by a random rotation of ~deg degrees."""
    rng = np.random.default_rng(seed)
    m, d, _ = truth_rotations.shape
    out = np.empty_like(truth_rotations)
    for i in range(m):
        a = rng.standard_normal((d, d))
        a = 0.5 * (a - a.T)
        a *= np.radians(deg) / max(np.linalg.norm(a, 2), 1e-12)
        w, v = np.linalg.eig(a)
        e = (v @ np.diag(np.exp(w)) @ np.linalg.inv(v)).real
        out[i] = e @ truth_rotations[i]
    return out


def test_registered():
    for name in ("spectral", *PAPER_SOLVERS):
        assert name in SOLVERS


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("solver", ["spectral", "reg-admm", *PAPER_SOLVERS])
def test_clean_problems_recovered(solver, d):
    problem, truth = make_problem(16, d=d, degree=5, nodes_per_pair=8, noise=0.0, seed=d)
    res = solve(problem, solver=solver)
    assert rotation_errors_deg(res.rotations, truth.rotations).max() < 1e-5
    assert res.certified
    if solver in PAPER_SOLVERS:
        # From a start 30 degrees away from the truth the iterations have real work to do.
        init = _perturbed(truth.rotations, 30.0, seed=d)
        res = solve(problem, solver=solver, init=init, tol=1e-10, max_iter=5000)
        assert res.converged, res.stats
        assert rotation_errors_deg(res.rotations, truth.rotations).max() < 1e-5
        assert res.certified


@pytest.mark.parametrize("solver", ["gpm", "balm"])
def test_matrix_free_paths(solver):
    problem, truth = make_problem(30, d=3, degree=6, nodes_per_pair=8, noise=0.0, seed=4)
    init = _perturbed(truth.rotations, 20.0, seed=1)
    res = solve(problem, solver=solver, method="matrix-free", init=init, tol=1e-10, max_iter=3000)
    assert res.method == "matrix-free" and res.converged
    assert rotation_errors_deg(res.rotations, truth.rotations).max() < 1e-5
    if solver == "balm":
        assert res.stats["x_solver"] == "block-cg" and res.stats["cg_steps"] > 0


def test_gpm_cost_is_monotone():
    problem, _ = make_problem(25, d=3, degree=5, nodes_per_pair=8, noise=0.3, seed=7)
    init = random_rotations(np.random.default_rng(0), 25, 3)  # a poor start: many iterations
    res = solve(problem, solver="gpm", init=init, tol=1e-9, max_iter=400)
    f = np.array([h["objective"] for h in res.history])
    assert len(f) > 20
    assert np.all(np.diff(f) <= 1e-12 * f[0]), np.diff(f).max()
    assert res.stats["cost_increases"] == 0
    assert res.stats["alpha"] >= res.stats["lambda_max"] * (1 - 1e-12)


def test_c_admm_and_reg_admm_agree_at_low_noise():
    problem, _ = make_problem(20, d=3, degree=6, nodes_per_pair=10, noise=0.02, seed=2)
    a = solve(problem, solver="c-admm", tol=1e-8, max_iter=5000)
    b = solve(problem, solver="reg-admm")
    assert a.stats["rank"] == 3 and a.stats["tight"]
    assert a.certified and b.certified
    diff = rotation_angle_deg(np.einsum("mji,mjk->mik", a.rotations, b.rotations))
    assert diff.max() < 1e-4, diff.max()
    assert a.objective == pytest.approx(b.objective, rel=1e-7)
    # Tight relaxation: the SDP optimum equals the rank-d optimum.
    assert a.stats["sdp_objective"] == pytest.approx(b.objective, rel=1e-5)


def test_c_admm_rank_is_d_at_zero_noise():
    for d in (2, 3):
        problem, _ = make_problem(15, d=d, degree=5, nodes_per_pair=8, noise=0.0, seed=5)
        res = solve(
            problem, solver="c-admm", init=random_rotations(np.random.default_rng(1), 15, d)
        )
        assert res.stats["rank"] == d, res.stats["eigenvalues_over_M"]
        ev = np.array(res.stats["eigenvalues_over_M"])
        assert np.allclose(ev[:d], 1.0, atol=1e-4) and np.all(ev[d:] < 1e-4)


def test_c_admm_rank_exceeds_d_at_high_noise():
    problem, _ = make_problem(12, d=2, degree=4, nodes_per_pair=4, noise=2.0, seed=1)
    res = solve(problem, solver="c-admm", tol=1e-7, max_iter=5000)
    assert res.stats["rank"] > 2 and res.stats["rounded"]
    assert not res.certified  # rounded from a non-tight relaxation
    assert res.stats["sdp_objective"] <= res.objective * (1 + 1e-6)  # relaxation bound


def test_balm_converges_to_kkt_point():
    problem, _ = make_problem(25, d=3, degree=5, nodes_per_pair=8, noise=0.1, seed=3)
    init = random_rotations(np.random.default_rng(2), 25, 3)
    tol = 1e-8
    res = solve(problem, solver="balm", init=init, tol=tol, max_iter=2000)
    assert res.converged
    assert res.certificate.kkt_residual <= tol
    assert res.stats["kkt_residual_final"] <= tol
    assert res.history[-1]["primal_residual"] <= tol


@pytest.mark.parametrize("solver", PAPER_SOLVERS)
def test_reflections_honoured(solver):
    problem, _ = make_problem(12, d=3, degree=5, nodes_per_pair=8, noise=0.0, seed=11)
    coords = problem.coords.copy()
    coords[problem.patch == 5] *= np.array([1.0, 1.0, -1.0])  # a mirrored scan
    mirrored = PatchProblem(coords, problem.patch, problem.node)
    res = solve(mirrored, solver=solver, allow_reflections=True, tol=1e-10, max_iter=3000)
    dets = np.linalg.det(res.rotations)
    assert np.sum(dets < 0) == 1 and res.objective < 1e-10
    so = solve(mirrored, solver=solver, tol=1e-8, max_iter=500)
    assert np.all(np.linalg.det(so.rotations) > 0) and so.objective > 1e-3


def test_c_admm_refuses_above_size_limit():
    limit = c_admm_module.C_ADMM_MAX_N
    m = limit // 3 + 1
    problem, _ = make_problem(m, d=3, degree=4, nodes_per_pair=4, seed=0)
    with pytest.raises(ConfigError, match=str(limit)):
        solve(problem, solver="c-admm")
