"""The tuned peers of issue 13, item 4 (bench.peers.open3d_tuned, bench.peers.kiss): their
conventions on exact data, and each on one small synthetic set, so a frame or scale
mistake cannot make a peer look worse (or better) than it is. Some seconds."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("open3d")


def _random_pose(rng, turn_deg, shift):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    axis = rng.normal(size=3)
    T[:3, :3] = Rotation.from_rotvec(np.radians(turn_deg) * axis / np.linalg.norm(axis)).as_matrix()
    T[:3, 3] = shift
    return T


def test_maximum_spanning_tree_keeps_the_heaviest_edges():
    from bench.peers.open3d_tuned import maximum_spanning_tree

    w = {(0, 1): 0.9, (1, 2): 0.2, (0, 2): 0.5, (2, 3): 0.4, (1, 3): 0.8, (4, 5): 0.3}
    assert maximum_spanning_tree(6, w) == {(0, 1), (1, 3), (0, 2), (4, 5)}


def test_kiss_matcher_pose_recovers_a_known_motion_at_object_scale():
    """KISS-Matcher works at its LiDAR voxel on scaled copies: the transform must come back
    in the data's units (a millimetre-sized voxel, as on the bunny)."""
    pytest.importorskip("kiss_matcher")
    import trimesh

    from bench.peers.kiss import kiss_matcher_pose
    from data_synth import load_mesh

    P = (
        trimesh.sample.sample_surface(load_mesh("builtin"), 20000, seed=2)[0] * 0.1
    )  # an object a tenth of a unit across: voxel far below KISS-Matcher's minimum
    T = _random_pose(np.random.default_rng(0), 70.0, [0.03, -0.02, 0.05])
    source = (P - T[:3, 3]) @ T[:3, :3]  # T maps source onto P
    voxel = 0.02 * np.linalg.norm(np.ptp(P, axis=0))
    T_est, stats = kiss_matcher_pose(source, P, voxel)
    assert stats["kiss_valid"]
    turn = np.degrees(np.arccos(np.clip((np.trace(T_est[:3, :3].T @ T[:3, :3]) - 1) / 2, -1, 1)))
    assert turn < 1.0, turn
    assert np.linalg.norm(T_est[:3, 3] - T[:3, 3]) < 0.5 * voxel


def test_open3d_tuned_recovers_whole_object_clouds_in_random_frames():
    """Five samplings of the whole builtin object, each in a random frame: every pair
    overlaps completely, so the tuned pipeline (RANSAC, ICP, spanning tree, pose graph)
    must return the true poses; a frame or edge-direction mistake would not."""
    import trimesh

    from bench.peers.open3d_tuned import run_open3d_tuned
    from data_synth import load_mesh
    from mvreg.metrics import pose_errors

    mesh = load_mesh("builtin")
    rng = np.random.default_rng(4)
    T_true = [_random_pose(rng, rng.uniform(20, 170), rng.normal(size=3)) for _ in range(5)]
    clouds, sensors = [], []
    for k, T in enumerate(T_true):
        world = trimesh.sample.sample_surface(mesh, 6000, seed=k)[0]
        clouds.append((world - T[:3, 3]) @ T[:3, :3])  # scan frame: T maps it to the world
        sensors.append((mesh.centroid - T[:3, 3]) @ T[:3, :3])  # normals all inwards
    r = run_open3d_tuned(clouds, 0.02 * float(np.linalg.norm(mesh.extents)), sensors, seed=0)
    assert sorted(r["T"]) == list(range(5))
    assert len(r["tree"]) == 4
    e = pose_errors(np.stack([r["T"][k] for k in range(5)]), np.stack(T_true))
    assert e.rotation_deg.max() < 0.5, e.rotation_deg


def test_peers_generalization_quick_run(tmp_path):
    """scripts/bench_peers_generalization.py on its smallest case: every method's row is
    consistent, mvreg's matches what the generalization benchmark reads from its run,
    and the report is written."""
    pytest.importorskip("kiss_matcher")
    import json

    from bench.peers_generalization import METHODS, main

    summary = main(["--quick", "--work", str(tmp_path / "work"), "--out", str(tmp_path / "out")])
    doc = json.loads((tmp_path / "out" / "peers_generalization.json").read_text())
    (row,) = doc["rows"]
    assert (row["mesh"], row["seed"], row["resolution"]) == ("builtin:1", 0, "tiny")
    for m in METHODS:
        x = row[m]
        assert 0 <= x["within"] <= x["registered"] <= 5 and x["seconds"] > 0
        assert x["fully_within"] == (x["within"] == 5)
        assert x["claimed_wrong"] == bool(x["claims_all"] and x["worst_rot"] and x["worst_rot"] > 2)
        assert summary[m]["nonsymmetric_runs"] == 1
    out = tmp_path / "work" / "builtin_1-s0-tiny-v5" / "out"
    report = json.loads((out / "report.json").read_text())
    assert row["mvreg"]["registered"] == len(report["registered"])
    assert row["mvreg"]["claims_all"] == (row["mvreg"]["exit_code"] == 0)
    md = (tmp_path / "out" / "peers_generalization.md").read_text()
    assert "open3d-tuned" in md and "kiss-matcher+mvreg" in md and "builtin:1" in md
