"""REG-ADMM, C, translations and certificates against ground truth (issue 2)."""

from __future__ import annotations

import numpy as np
import pytest

from data_synth.problems import make_problem
from mvreg.errors import ConfigError, DisconnectedError, IllPosedError, ProblemError
from mvreg.geometry import random_rotations, rotation_angle_deg
from mvreg.metrics import rotation_errors_deg, translation_errors
from mvreg.solver import PatchProblem, RegOperator, certify, solve
from mvreg.solver.blocks import x_from_rotations
from mvreg.solver.certificate import multipliers
from mvreg.solver.spectral import lambda_max


def _errors(res, truth):
    rot = rotation_errors_deg(res.rotations, truth.rotations)
    tr = translation_errors(res.rotations, res.translations, truth.rotations, truth.translations)
    scale = np.ptp(truth.translations, axis=0).max()
    return rot.max(), tr.max() / scale


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("method", ["dense", "matrix-free"])
def test_clean_problems_recovered_exactly(d, method):
    problem, truth = make_problem(40, d=d, degree=6, noise=0.0, seed=3)
    res = solve(problem, method=method)
    rot, tr = _errors(res, truth)
    assert rot < 1e-6, rot
    assert tr < 1e-8, tr
    assert res.certified
    assert res.certificate.kkt_residual < 1e-10
    assert res.objective < 1e-12


def test_dense_and_matrix_free_agree_on_noisy_data():
    problem, truth = make_problem(80, d=3, noise=0.02, seed=5)
    a = solve(problem, method="dense")
    b = solve(problem, method="matrix-free")
    assert a.method == "dense" and b.method == "matrix-free"
    assert a.certified and b.certified
    diff = rotation_angle_deg(np.einsum("mji,mjk->mik", a.rotations, b.rotations))
    assert diff.max() < 1e-6, diff.max()
    assert np.max(np.abs(a.translations - b.translations)) < 1e-8 * np.ptp(a.translations)
    assert abs(a.objective - b.objective) <= 1e-9 * a.objective
    # The optimum is closer to the data than the truth is (least squares), and close to it.
    rot, _ = _errors(a, truth)
    assert rot < 5.0


def test_trace_cg_equals_reg_residual_at_optimal_t_z():
    problem, truth = make_problem(25, d=3, noise=0.05, seed=1)
    op = RegOperator(problem)
    t, z = op.translations(truth.rotations)
    reg = op.residual(truth.rotations, t, z)
    assert reg > 0
    assert op.objective(truth.rotations) * op.norm.scale**2 == pytest.approx(reg, rel=1e-9)
    # The closed-form t, z are optimal: perturbing them increases the REG cost.
    rng = np.random.default_rng(0)
    assert op.residual(truth.rotations, t + 1e-3 * rng.standard_normal(t.shape)) > reg
    # Dense C matches the operator, is symmetric PSD with nullity d for clean data.
    clean, ct = make_problem(25, d=3, noise=0.0, seed=1)
    cop = RegOperator(clean)
    c = cop.dense()
    v = rng.standard_normal((cop.n, 2))
    cop._dense = None
    assert np.allclose(c @ v, cop.matvec(v), atol=1e-10)
    w = np.linalg.eigvalsh(c)
    assert np.all(w[:3] < 1e-10 * w[-1]) and w[3] > 1e-4 * w[-1]
    # Zero at the truth up to rounding (relative to the size of C).
    assert cop.objective(ct.rotations) < 1e-13 * np.trace(c)


def test_objective_equals_reg_residual_with_long_tracks():
    """C, B, S assembled as sparse products must give the REG cost at the optimal t, z
    for tracks of many observations (up to 12 patches per node, uneven weights), not
    only the two-observation tracks of make_problem."""
    rng = np.random.default_rng(4)
    m, nodes = 30, 400
    patch, node = [], []
    for k in range(nodes):
        seen = rng.choice(m, rng.integers(2, 13), replace=False)
        patch += seen.tolist()
        node += [k] * len(seen)
    patch, node = np.array(patch), np.array(node)
    R, t0 = random_rotations(rng, m), rng.normal(size=(m, 3))
    z = rng.normal(size=(nodes, 3))
    coords = np.einsum("kji,kj->ki", R[patch], z[node] - t0[patch]) + 0.01 * rng.normal(
        size=(len(patch), 3)
    )
    problem = PatchProblem(coords, patch, node, rng.uniform(0.2, 1.0, len(patch)))
    op = RegOperator(problem)
    Q = random_rotations(rng, m)
    for rot in (R, Q):
        t, zz = op.translations(rot)
        assert op.objective(rot) * op.norm.scale**2 == pytest.approx(
            op.residual(rot, t, zz), rel=1e-9
        )
    c = op.dense()
    assert np.allclose(c, c.T) and np.linalg.eigvalsh(c)[0] > -1e-9 * np.abs(c).max()


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_certificate_true_for_clean_and_low_noise(noise):
    problem, _ = make_problem(60, d=3, noise=noise, seed=7)
    res = solve(problem)
    c = res.certificate
    assert c.certified
    assert c.min_eigenvalue > 0
    assert c.relative_gap <= 1e-6


def _stationary_non_optimal(method_dense: bool):
    """M = 2, d = 2: f depends on the relative rotation only, so rotating one patch by pi
    from the optimum gives the other stationary point, the maximum."""
    rng = np.random.default_rng(2)
    pts = rng.uniform(-1, 1, size=(8, 2))
    rot = random_rotations(rng, 2, 2)
    coords = np.concatenate([pts @ rot[0], pts @ rot[1] + 0.01 * rng.standard_normal((8, 2))])
    problem = PatchProblem(coords, np.repeat([0, 1], 8), np.tile(np.arange(8), 2))
    op = RegOperator(problem)
    best = solve(problem)
    flip = np.array([[-1.0, 0.0], [0.0, -1.0]])
    R = best.rotations.copy()
    R[1] = R[1] @ flip
    return op, R, best


@pytest.mark.parametrize("dense", [True, False])
def test_certificate_false_for_non_optimal_stationary_point(dense):
    op, R, best = _stationary_non_optimal(dense)
    lmax = lambda_max(op, True)
    X = x_from_rotations(R)
    _, grad = multipliers(X, op.matvec(X), 2)
    assert np.linalg.norm(grad) < 1e-10  # a KKT point (Lemma 1)...
    cert = certify(op, R, lmax, dense=dense)
    assert not cert.certified  # ...but not the global optimum
    assert cert.min_eigenvalue < -1e-3
    assert cert.objective > best.objective
    assert best.certified


def test_admm_fixed_points_are_kkt_points():
    problem, _ = make_problem(20, d=3, noise=0.005, seed=4, graph="complete")
    res = solve(problem, polish=False, max_iter=3000, rho=5.0, tol=1e-9)
    assert res.converged and res.stats["stopped_by"] == "residuals"
    assert res.certificate.kkt_residual < 1e-6
    # [C G]_ii symmetric (Lemma 1 b) <=> small KKT residual; the limit is the optimum.
    assert res.certified
    best = solve(problem)
    diff = rotation_angle_deg(np.einsum("mji,mjk->mik", res.rotations, best.rotations))
    assert diff.max() < 1e-3


def test_rho_policy_theorem4_is_theorem4_and_recorded():
    problem, _ = make_problem(30, d=3, noise=0.3, seed=2)
    res = solve(problem, max_iter=60, reg_admm={"rho_policy": "theorem4"})
    first = res.rho_history[0]
    lam = res.stats["lambda_d_plus_1"]
    assert first["reason"] == "Theorem 4 bound"
    assert first["rho"] == pytest.approx(lam / (2 * 30 * np.sqrt(3)), rel=1e-9)
    for change in res.rho_history[1:]:
        assert change["rho"] > change["previous"] and "stalled" in change["reason"]


def test_invariance_to_global_motion_and_patch_order():
    problem, truth = make_problem(30, d=3, noise=0.02, seed=9)
    base = solve(problem)
    # The same rigid motion of every patch's local coordinates: poses change by g^-1.
    rng = np.random.default_rng(1)
    g = random_rotations(rng, 1, 3)[0]
    shift = np.array([3.0, -2.0, 5.0])
    moved = PatchProblem(problem.coords @ g.T + shift, problem.patch, problem.node)
    res = solve(moved)
    r_back = np.einsum("mij,jk->mik", res.rotations, g)  # R'_i = R_i g^T up to the gauge
    assert rotation_errors_deg(r_back, base.rotations).max() < 1e-7
    assert res.objective == pytest.approx(base.objective, rel=1e-8)
    # Permuting patches permutes the solution (up to the gauge).
    perm = rng.permutation(30)
    inv = np.argsort(perm)
    permuted = PatchProblem(problem.coords, inv[problem.patch], problem.node)
    res_p = solve(permuted)
    assert rotation_errors_deg(res_p.rotations[inv], base.rotations).max() < 1e-7
    assert res_p.objective == pytest.approx(base.objective, rel=1e-8)


def test_reflections_allowed_gives_o_d():
    problem, truth = make_problem(20, d=3, noise=0.0, seed=11)
    coords = problem.coords.copy()
    coords[problem.patch == 5] *= np.array([1.0, 1.0, -1.0])  # a mirrored scan
    mirrored = PatchProblem(coords, problem.patch, problem.node)
    res = solve(mirrored, allow_reflections=True)
    dets = np.linalg.det(res.rotations)
    assert res.certified and res.objective < 1e-12
    assert np.sum(dets < 0) == 1 and dets[5] * dets[0] < 0
    so = solve(mirrored)
    assert np.all(np.linalg.det(so.rotations) > 0) and so.objective > 1e-3


# ---------------------------------------------------------------- bad input
def _ok():
    problem, _ = make_problem(6, d=3, noise=0.0, seed=0)
    return problem.coords, problem.patch, problem.node


def test_nan_coords_rejected():
    c, p, n = _ok()
    c = c.copy()
    c[5, 1] = np.nan
    with pytest.raises(ProblemError, match="NaN"):
        PatchProblem(c, p, n)


def test_bad_indices_rejected():
    c, p, n = _ok()
    with pytest.raises(ProblemError, match="negative"):
        PatchProblem(c, np.where(np.arange(len(p)) == 3, -1, p), n)
    with pytest.raises(ProblemError, match="out of range"):
        PatchProblem(c, p, n, num_patches=3)
    with pytest.raises(ProblemError, match="more than once"):
        PatchProblem(np.r_[c, c[:1]], np.r_[p, p[:1]], np.r_[n, n[:1]])


def test_empty_patch_rejected():
    c, p, n = _ok()
    with pytest.raises(ProblemError, match="no observations: 6"):
        PatchProblem(c, p, n, num_patches=7)


def test_ill_posed_patch_named():
    c, p, n = _ok()
    # Patch 6 shares only 2 nodes with the rest: its rotation is not determined.
    c2 = np.r_[c, np.array([[0.1, 0.2, 0.3], [0.5, -0.1, 0.2]])]
    p2 = np.r_[p, [6, 6]]
    n2 = np.r_[n, n[:2]]
    with pytest.raises(IllPosedError, match="6") as e:
        PatchProblem(c2, p2, n2, patch_names=[f"s{i}" for i in range(7)])
    assert e.value.patches == ["s6"]


def test_disconnected_components_named():
    a, _ = make_problem(4, d=3, seed=1)
    b, _ = make_problem(3, d=3, seed=2)
    coords = np.r_[a.coords, b.coords]
    patch = np.r_[a.patch, b.patch + 4]
    node = np.r_[a.node_ids[a.node_index], b.node_ids[b.node_index] + 10_000]
    with pytest.raises(DisconnectedError) as e:
        PatchProblem(coords, patch, node)
    assert e.value.components == [["0", "1", "2", "3"], ["4", "5", "6"]]


def test_absurd_parameters_rejected():
    problem, _ = make_problem(5, d=3, seed=0)
    for kw in ({"rho": -1.0}, {"rho": "fast"}, {"max_iter": 0}, {"solver": "magic"}):
        with pytest.raises(ConfigError):
            solve(problem, **kw)


# ---------------------------------------------------------------- registry and contract
def test_registry_matches_config_names_and_options():
    from pydantic import BaseModel

    from mvreg.config.solve import SOLVER_NAMES, SolveConfig
    from mvreg.solver import SOLVERS

    assert tuple(SOLVERS) == SOLVER_NAMES
    cfg = SolveConfig()
    assert cfg.solver == next(iter(SOLVERS))
    for name, entry in SOLVERS.items():
        assert callable(entry.load())
        assert isinstance(cfg.options(name), BaseModel)
        assert cfg.options(name) is getattr(cfg, entry.options_field)


def test_solver_base_and_solve_config_import_nothing_of_the_algorithms():
    import ast
    from pathlib import Path

    import mvreg

    root = Path(mvreg.__file__).parent
    allowed = {"solver/base.py": set(), "config/solve.py": {"mvreg.errors"}}
    for rel, ok in allowed.items():
        tree = ast.parse((root / rel).read_text())
        found = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        found |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        assert {m for m in found if m.split(".")[0] == "mvreg"} <= ok, rel


def test_shared_keys_fill_every_solver_section():
    from mvreg.config import load_config
    from mvreg.config.solve import SolveConfig

    cfg = SolveConfig(max_iter=50, rho=2.0, tol=1e-8, polish=False)
    for section in (cfg.reg_admm, cfg.gpm, cfg.balm, cfg.c_admm):
        assert section.max_iter == 50 and section.tol == 1e-8 and not section.polish
    assert cfg.reg_admm.rho == 2.0 and cfg.c_admm.rho == 2.0
    assert SolveConfig().reg_admm.polish and not SolveConfig().gpm.polish
    reg = load_config(**{"solve.max_iter": 7, "solve.reg_admm.rho": 3.0})
    assert reg.solve.balm.max_iter == 7 and reg.solve.reg_admm.rho == 3.0
    with pytest.raises(ConfigError, match="unknown solver"):
        load_config(**{"solve.solver": "magic"})
    with pytest.raises(ConfigError, match="rho"):
        load_config(**{"solve.reg_admm.rho": -1.0})


def test_config_and_keyword_overrides_agree():
    from mvreg.config.solve import GpmOptions, SolveConfig

    problem, _ = make_problem(15, d=3, noise=0.05, seed=2)
    a = solve(problem, SolveConfig(solver="gpm", gpm=GpmOptions(max_iter=7)))
    b = solve(problem, solver="gpm", max_iter=7)
    c = solve(problem, SolveConfig(solver="gpm"), max_iter=7)
    assert a.iterations == b.iterations == c.iterations == 7
    assert np.array_equal(a.rotations, b.rotations) and np.array_equal(a.rotations, c.rotations)


@pytest.mark.parametrize("solver", ["reg-admm", "spectral", "gpm", "balm", "c-admm"])
def test_every_solver_calls_back_with_iteration_records(solver):
    from mvreg.solver import IterationRecord

    problem, _ = make_problem(12, d=3, noise=0.3, seed=5)
    init = random_rotations(np.random.default_rng(0), 12, 3)
    got = []
    res = solve(problem, solver=solver, init=init, max_iter=30, callback=got.append)
    assert all(isinstance(r, IterationRecord) for r in got)
    assert len(got) == len(res.history) == res.iterations
    assert [r.to_dict() for r in got] == res.history
    for r in got:
        assert np.isfinite(r.objective) and r.objective >= 0


@pytest.fixture(scope="module")
def six_scans(tmp_path_factory):
    from data_synth import synthesize_scans

    folder = tmp_path_factory.mktemp("six") / "scans"
    synthesize_scans("builtin", folder, views=6, points_per_scan=3000, seed=0, random_frames=True)
    return folder


@pytest.mark.parametrize("solver", ["reg-admm", "spectral", "gpm", "balm", "c-admm"])
def test_register_runs_with_every_solver(solver, six_scans):
    """Issue 16: register with a non-default solver crashed in the pipeline's callback
    (the solver handed dicts where the pipeline expects IterationRecord)."""
    from mvreg.pipeline import register

    reg = register(six_scans, **{"solve.solver": solver, "refine.rounds": 0})
    assert reg.all_registered, reg.unregistered
    assert reg.solve.solver == solver
