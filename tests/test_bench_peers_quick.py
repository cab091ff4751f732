"""Conventions of the peer benchmark's adapters (bench.peers, scripts/bench_peers.py), on
exact data.

Open3D's pose graph and GTSAM's between factors each have their own direction and tangent
convention; a sign or frame mistake would make a peer look worse than it is. Here every
adapter must recover known poses from noise-free edges. A few seconds.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("gtsam")
pytest.importorskip("open3d")


@pytest.fixture(scope="module")
def bp():
    from bench.peers.gtsam import gtsam_solve
    from bench.peers.open3d import o3d_optimize, o3d_prepare, run_open3d_fed
    from bench.peers.patches import kabsch_edges

    return SimpleNamespace(
        gtsam_solve=gtsam_solve,
        kabsch_edges=kabsch_edges,
        o3d_optimize=o3d_optimize,
        o3d_prepare=o3d_prepare,
        run_open3d_fed=run_open3d_fed,
    )


def _random_poses(rng, n, scale=1.0):
    from scipy.spatial.transform import Rotation

    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=rng.integers(1 << 31)).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3)) * scale
    return T


def _max_errors(T_est: dict, T_true: np.ndarray):
    from mvreg.metrics import pose_errors

    keys = sorted(T_est)
    e = pose_errors(np.stack([T_est[k] for k in keys]), T_true[keys])
    return float(e.rotation_deg.max()), float(e.translation.max())


def test_gtsam_recovers_noise_free_patch_problem(bp):
    from data_synth.problems import make_problem

    problem, truth = make_problem(30, d=3, degree=5, nodes_per_pair=12, noise=0.0, seed=1)
    rel, cov = bp.kabsch_edges(problem, truth.edges)
    for i, j in truth.edges[:5]:  # T_i_j = T_world_i^-1 T_world_j
        Ti = np.eye(4)
        Ti[:3, :3], Ti[:3, 3] = truth.rotations[i], truth.translations[i]
        Tj = np.eye(4)
        Tj[:3, :3], Tj[:3, 3] = truth.rotations[j], truth.translations[j]
        np.testing.assert_allclose(rel[(int(i), int(j))], np.linalg.inv(Ti) @ Tj, atol=1e-8)
    # Noise-free fits have zero residual: give the covariances a floor for the solver.
    cov = {k: c + 1e-8 * np.eye(6) for k, c in cov.items()}
    g = bp.gtsam_solve(30, rel, cov)
    T_true = np.tile(np.eye(4), (30, 1, 1))
    T_true[:, :3, :3], T_true[:, :3, 3] = truth.rotations, truth.translations
    rot, tr = _max_errors(g["T"], T_true)
    assert rot < 1e-4 and tr < 1e-4
    assert g["certified"]


def test_open3d_and_gtsam_on_mvreg_style_edges(bp):
    """Point clouds of one object in 5 frames; exact T_i_j as mvreg's pairs would give them.
    Open3D's pose graph (fed) and GTSAM (with the converted information matrices) must
    both return the true poses from a perturbed start."""
    rng = np.random.default_rng(0)
    n = 5
    obj = rng.uniform(-1, 1, size=(3000, 3)) * [1.0, 0.7, 0.4]
    T_true = _random_poses(rng, n, scale=2.0)
    clouds = [(obj - T[:3, 3]) @ T[:3, :3] for T in T_true]  # local = R^T (p - t)
    v = 0.1
    prep = [bp.o3d_prepare(c, v) for c in clouds]
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (0, 2), (1, 3), (0, 4)]
    rel = {(i, j): np.linalg.inv(T_true[i]) @ T_true[j] for i, j in pairs}
    fed = bp.run_open3d_fed(n, rel, prep, v, 0.0)
    rot, tr = _max_errors(fed["T"], T_true)
    assert rot < 1e-3 and tr < 1e-3
    g = bp.gtsam_solve(n, rel, fed["cov"])
    rot, tr = _max_errors(g["T"], T_true)
    assert rot < 1e-3 and tr < 1e-3


def test_open3d_optimizer_edge_direction(bp):
    """o3d_optimize with edges (source, target, T_target_source) and a perturbed start."""
    rng = np.random.default_rng(3)
    n = 4
    T_true = _random_poses(rng, n)
    T_true[0] = np.eye(4)  # reference node 0 is the world
    edges = []
    for s, t in [(0, 1), (1, 2), (2, 3), (0, 3), (1, 3)]:
        T_t_s = np.linalg.inv(T_true[t]) @ T_true[s]
        edges.append((s, t, T_t_s, np.eye(6) * 100.0, (s, t) != (0, 1)))
    init = {k: T_true[k].copy() for k in range(n)}
    for k in range(1, n):
        init[k][:3, 3] += rng.normal(scale=0.01, size=3)
    out = bp.o3d_optimize(n, edges, init, 0.1)
    for k in range(n):
        np.testing.assert_allclose(out[k], T_true[k], atol=1e-4)


def test_rerun_global_runs_register_with_another_solver(tmp_path):
    """The mvreg solver variants rerun the pipeline on the cached stages of a first run
    (public staged API: run_pipeline with a mode replaying them); this must keep working
    as mvreg.pipeline changes."""
    from bench.peers.mvreg_run import rerun_global, run_default
    from data_synth import synthesize_scans

    synthesize_scans(
        "builtin", tmp_path / "s", views=4, points_per_scan=3000, seed=0, random_frames=True
    )
    first, cached = run_default(tmp_path / "s", None, 0)
    again = rerun_global(
        tmp_path / "s", cached, seed=0, **{"solve.solver": "spectral", "refine.rounds": 0}
    )
    assert set(again.T_world_scan) == set(first.T_world_scan)
    assert again.timings["pairwise"] < 1.0  # the cached pairs, not a new alignment
    assert again.config.solve.solver == "spectral"
    # Same settings on the same cached stages: the same poses as the first run.
    same = rerun_global(tmp_path / "s", cached, seed=0)
    for name, T in first.T_world_scan.items():
        np.testing.assert_allclose(same.T_world_scan[name], T, atol=1e-9)
