"""The solver on overlap graphs whose factorization fills in (issue 15, random graph rows):
PARDISO's forecast decides between the direct and the iterative paths, and the iterative
spectrum (LOBPCG) agrees with the shift-invert one."""

from __future__ import annotations

import numpy as np
import pytest

from data_synth.problems import make_problem
from mvreg.metrics import rotation_errors_deg
from mvreg.solver import RegOperator, pardiso, shift_invert, solve
from mvreg.solver.spectral import lobpcg_spectrum, spectral_rotations, spectrum

needs_pardiso = pytest.mark.skipif(not pardiso.available(), reason="MKL PARDISO not loadable")


@needs_pardiso
def test_forecast_tells_an_expander_from_a_mesh_like_graph():
    """Same size and degree, the random graph's factor is many times denser."""
    fills = {}
    for graph in ("geometric", "random"):
        problem, _ = make_problem(1500, d=3, noise=0.01, graph=graph, seed=0)
        op = RegOperator(problem)
        assert shift_invert.direct_feasible(op)  # both affordable at this size
        f = op.factor_forecast
        assert f["direct"] and f["factor_nnz"] > 0 and f["factor_flops"] > 0
        fills[graph] = f
    assert fills["random"]["factor_flops"] > 10 * fills["geometric"]["factor_flops"]
    assert fills["random"]["factor_nnz"] > 3 * fills["geometric"]["factor_nnz"]


def testlobpcg_spectrum_matches_shift_invert():
    problem, _ = make_problem(700, d=3, noise=0.02, graph="random", seed=3)
    op = RegOperator(problem)
    ref = spectrum(op, dense=False, seed=0)  # shift-invert (factorization affordable here)
    got = lobpcg_spectrum(op, 4, ref.largest, seed=1)
    np.testing.assert_allclose(got.smallest, ref.smallest, rtol=1e-3)
    # The same d-dimensional eigenspace: all principal angles ~ 0.
    s = np.linalg.svd(ref.vectors[:, :3].T @ got.vectors[:, :3], compute_uv=False)
    assert s.min() > 1 - 1e-6


@needs_pardiso
def test_iterative_path_certifies_the_same_solution(monkeypatch):
    """With every factorization forecast too costly, the solve takes the iterative paths
    (LOBPCG spectrum, unpreconditioned Newton CG, LOBPCG certificate) and reaches the same
    certified optimum as the direct paths."""
    problem, truth = make_problem(700, d=3, noise=0.02, graph="random", seed=4)
    direct = solve(problem, method="matrix-free")
    assert direct.stats["factor_forecast"]["direct"]
    monkeypatch.setattr(shift_invert, "FACTOR_MAX_FLOPS", 0.0)
    iterative = solve(problem, method="matrix-free")
    assert iterative.stats["factor_forecast"]["direct"] is False
    assert direct.certified and iterative.certified
    rel = abs(iterative.objective - direct.objective) / direct.objective
    assert rel < 1e-6
    err = rotation_errors_deg(iterative.rotations, direct.rotations)
    assert err.max() < 1e-3
    assert np.median(rotation_errors_deg(iterative.rotations, truth.rotations)) < 1.0


def test_tangent_block_jacobi_cuts_the_newton_cg_steps(monkeypatch):
    """Without a factorization the polish's Newton CG is preconditioned by the per-patch
    blocks of the Riemannian Hessian: the same KKT point in fewer CG steps."""
    import mvreg.solver.polish as polish_mod

    problem, _ = make_problem(800, d=3, noise=0.04, graph="random", seed=5)
    op = RegOperator(problem)
    spec = spectrum(op, dense=False, seed=0)
    R0 = spectral_rotations(spec, 3)
    monkeypatch.setattr(polish_mod, "direct_feasible", lambda op: False)
    monkeypatch.setattr(polish_mod, "newton_direct_feasible", lambda op: False)
    R1, s1 = polish_mod.polish(op, R0, spec.largest, precondition=True)
    R2, s2 = polish_mod.polish(op, R0, spec.largest, precondition=False)
    assert s1.kkt_residual <= 1e-10 and s2.kkt_residual <= 1e-10
    assert abs(s1.objective - s2.objective) <= 1e-9 * abs(s2.objective)
    assert rotation_errors_deg(R1, R2).max() < 1e-4
    assert s1.cg_steps < 0.7 * s2.cg_steps, (s1.cg_steps, s2.cg_steps)
