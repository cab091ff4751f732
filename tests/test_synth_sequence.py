"""LiDAR sequence through a scene: ordered, timestamped, on the scene surface, reproducible."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from data_synth import build_scene, synthesize_sequence
from data_synth.sequence import loop_poses
from mvreg.errors import ConfigError, OutputExistsError
from mvreg.io.poses import read_poses_json, read_poses_tum

SMALL = dict(frames=8, points_per_scan=3000, n_objects=4, buildings=4, seed=1)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    out = tmp_path_factory.mktemp("sequence")
    return synthesize_sequence(None, out, noise=0.0, **SMALL)


def test_files_timestamps_and_poses(sequence):
    out = sequence.out_dir
    names = [f"scan_{k:03d}.ply" for k in range(8)]
    assert [p.name for p in sequence.scan_paths] == names
    timestamps = np.loadtxt(out / "timestamps.txt")
    np.testing.assert_allclose(timestamps, np.arange(8) / 10.0)
    poses = read_poses_json(out / "ground_truth.json")
    assert list(poses) == names
    tum_times, tum_poses = read_poses_tum(out / "ground_truth_tum.txt")
    np.testing.assert_allclose(tum_times, timestamps)
    for name, T_tum in zip(names, tum_poses, strict=True):
        np.testing.assert_allclose(T_tum, poses[name], atol=1e-12)
    gt = json.loads((out / "ground_truth.json").read_text())
    assert gt["units"] == "m"
    # A closed loop at constant height, the LiDAR facing along the path.
    positions = np.array([poses[n][:3, 3] for n in names])
    np.testing.assert_allclose(positions[:, 2], 1.8)
    steps = np.diff(np.vstack([positions, positions[:1]]), axis=0)
    headings = np.array([poses[n][:3, 0] for n in names])
    assert np.all(np.einsum("ij,ij->i", steps, headings) > 0.0)
    assert np.linalg.norm(steps, axis=1).max() < 15.0


def test_points_lie_on_the_scene_surface(sequence):
    # The scene is rebuilt from synth.json alone, then the scans are checked against it.
    synth = json.loads((sequence.out_dir / "synth.json").read_text())
    scene = build_scene(None, n_objects=4, buildings=4, seed=synth["scene"]["seed"])
    np.testing.assert_array_equal(scene.mesh.vertices, sequence.scene.mesh.vertices)
    raycasting = o3d.t.geometry.RaycastingScene()
    raycasting.add_triangles(
        o3d.core.Tensor(scene.mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(scene.mesh.faces.astype(np.uint32)),
    )
    poses = read_poses_json(sequence.out_dir / "ground_truth.json")
    for name, T in poses.items():
        points = np.asarray(o3d.io.read_point_cloud(str(sequence.out_dir / name)).points)
        assert len(points) > 1000
        world = points @ T[:3, :3].T + T[:3, 3]
        d = raycasting.compute_distance(o3d.core.Tensor(world.astype(np.float32))).numpy()
        assert d.max() < 1e-4  # metres; float32 coordinates of up to ~45 m
        # Objects and buildings are seen, not only the ground.
        assert np.mean(world[:, 2] > 0.1) > 0.1


def test_consecutive_scans_overlap(sequence):
    assert len(sequence.consecutive_overlap) == 8
    assert sequence.consecutive_overlap.min() > 0.5
    counts = np.array(sequence.point_counts)
    assert 0.7 * 3000 < counts.mean() < 1.3 * 3000


def test_same_seed_same_bytes(tmp_path):
    a = synthesize_sequence(None, tmp_path / "a", noise=0.002, outliers=0.01, **SMALL)
    b = synthesize_sequence(None, tmp_path / "b", noise=0.002, outliers=0.01, **SMALL)
    for pa, pb in zip(a.scan_paths, b.scan_paths, strict=True):
        assert pa.read_bytes() == pb.read_bytes()
    for name in ["synth.json", "ground_truth.json", "timestamps.txt"]:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


def test_sequence_from_a_mesh_file_and_errors(tmp_path, shared_data):
    bunny = shared_data / "meshes" / "stanford-bunny.obj"
    result = synthesize_sequence(
        [bunny], tmp_path / "bunny", frames=3, points_per_scan=2000, n_objects=3, buildings=0
    )
    objects = result.config["scene"]["objects"]
    assert [o["name"] for o in objects] == ["stanford-bunny.obj"] * 3
    assert all(2.0 <= o["diagonal_m"] <= 5.0 for o in objects)  # rescaled to metres
    with pytest.raises(OutputExistsError):
        synthesize_sequence(None, tmp_path / "bunny", frames=3)
    with pytest.raises(ConfigError, match="frames .* not 1"):
        synthesize_sequence(None, tmp_path / "x", frames=1)
    with pytest.raises(ConfigError, match="rate must be > 0 Hz, not -1"):
        synthesize_sequence(None, tmp_path / "x", rate_hz=-1.0)


def test_loop_poses_are_rigid():
    poses = loop_poses(16, (15.0, 10.0), 1.8)
    for T in poses:
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
