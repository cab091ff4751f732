"""The rerun recording: written, then read back with rerun's own reader (rerun.chunk)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from mvreg.viz import (
    NullRecorder,
    Recorder,
    RecordingFile,
    make_recorder,
    residual_colors,
    scan_colors,
    viridis,
)
from mvreg.viz import recorder as recorder_module

NAMES = ["bun000.ply", "scan 1.ply", "scan_2"]


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _scans(seed: int = 0, sizes=(300, 250, 400)):
    rng = np.random.default_rng(seed)
    points = [rng.normal(size=(n, 3)) * [1.0, 2.0, 0.5] for n in sizes]
    poses = []
    for _ in sizes:
        pose = np.eye(4)
        pose[:3, :3] = _rotation(rng)
        pose[:3, 3] = rng.normal(size=3)
        poses.append(pose)
    poses[0] = np.eye(4)
    return points, poses


def _unpack_rgba(packed) -> np.ndarray:
    packed = np.asarray(packed, dtype=np.uint32).reshape(-1)
    return np.stack([(packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255], -1)


def _write_full_run(path, **options):
    points, poses = _scans()
    objective = [10.0, 5.0, 2.5, 1.25, 1.0]
    primal = [1.0, 0.1, 0.01, 1e-3, 1e-4]
    rho = [1.0, 1.0, 2.0, 2.0, 4.0]
    world = [p @ pose[:3, :3].T + pose[:3, 3] for p, pose in zip(points, poses, strict=True)]
    merged = np.vstack(world)
    residuals = np.linspace(0.0, 1.0, len(merged))
    with make_recorder(path, recording_id="test-recording", **options) as rec:
        assert isinstance(rec, Recorder) and rec.enabled
        rec.log_config({"voxel_size": 0.05, "solver": {"name": "reg-admm", "max_iter": 5}})
        rec.log_raw_scans(NAMES, points)
        for step in range(5):
            rec.log_solver_iteration(
                step, objective=objective[step], primal_residual=primal[step], rho=rho[step]
            )
        rec.log_aligned(NAMES, points, poses)
        rec.log_pair_correspondences(NAMES[0], NAMES[1], world[0][:250], world[1][:250], 0.9)
        rec.log_residual_heatmap(merged, residuals)
        rec.log_ground_truth(NAMES, poses)
    return points, poses, objective, primal, rho, merged, residuals


def test_recording_holds_every_entity_read_back_by_rerun(tmp_path):
    target = tmp_path / "out" / "recording.rrd"
    points, poses, objective, primal, rho, merged, residuals = _write_full_run(target)

    assert sorted(p.name for p in target.parent.iterdir()) == ["recording.rrd"]
    rrd = RecordingFile(target)
    assert rrd.application_id == "mvreg" and rrd.recording_id == "test-recording"

    # Raw scans: static, as given, one color per scan.
    raw_colors = []
    for name, scan in zip(NAMES, points, strict=True):
        assert rrd.is_static(["raw", name])
        positions = rrd.latest(["raw", name], "Points3D:positions")
        np.testing.assert_allclose(positions, scan, atol=1e-6)
        raw_colors.append(tuple(_unpack_rgba(rrd.latest(["raw", name], "Points3D:colors"))[0]))
    assert len(set(raw_colors)) == len(NAMES)

    # Aligned scans: the pose as a transform, the points in the scan frame under it.
    for name, scan, pose, color in zip(NAMES, points, poses, raw_colors, strict=True):
        entity = ["world", "scans", name]
        assert rrd.is_static(entity)
        translation = rrd.latest(entity, "Transform3D:translation").reshape(3)
        rotation = rrd.latest(entity, "Transform3D:mat3x3").reshape(3, 3).T  # column-major
        np.testing.assert_allclose(translation, pose[:3, 3], atol=1e-6)
        np.testing.assert_allclose(rotation, pose[:3, :3], atol=1e-6)
        assert rrd.latest(entity, "TransformAxes3D:axis_length").item() > 0
        positions = rrd.latest(entity + ["points"], "Points3D:positions")
        np.testing.assert_allclose(positions, scan, atol=1e-6)
        colors = _unpack_rgba(rrd.latest(entity + ["points"], "Points3D:colors"))
        assert tuple(colors[0]) == color  # same color raw and aligned

    # Solver scalars on the solver_iteration timeline, one row per iteration.
    for entity, expected in [("objective", objective), ("primal_residual", primal), ("rho", rho)]:
        assert not rrd.is_static(f"solver/{entity}")
        steps, values = rrd.scalars(f"solver/{entity}")
        assert steps.tolist() == [0, 1, 2, 3, 4]
        np.testing.assert_allclose(values, expected)
    assert not rrd.has("solver/dual_residual")  # never given, never logged

    # Residual heat map: the merged cloud, its residuals and a viridis coloring.
    heat = ["residual_heatmap", "merged"]
    np.testing.assert_allclose(rrd.latest(heat, "Points3D:positions"), merged, atol=1e-5)
    np.testing.assert_allclose(rrd.latest(heat, "residual"), residuals, atol=1e-6)
    expected_colors, clip = residual_colors(residuals, 95.0)
    np.testing.assert_array_equal(
        _unpack_rgba(rrd.latest(heat, "Points3D:colors")), expected_colors
    )
    assert clip == pytest.approx(0.95)

    # Pair correspondences: one segment per match, and the ground truth poses.
    strips = rrd.column(["world", "pairs", f"{NAMES[0]}--{NAMES[1]}"], "LineStrips3D:strips")
    assert len(strips[-1]) == 200  # capped by max_lines_per_pair
    assert all(len(segment) == 2 for segment in strips[-1])
    for name in NAMES:
        assert rrd.has(["world", "ground_truth", name])

    config = rrd.latest("config", "TextDocument:text").item()
    assert '"voxel_size": 0.05' in config and "reg-admm" in config

    # The blueprint travels in the same file.
    views = {(v["class_identifier"], v["origin"]) for v in rrd.blueprint_views}
    assert {("3D", "raw"), ("3D", "world"), ("3D", "residual_heatmap")} <= views
    assert ("TimeSeries", "solver") in views
    assert ("TextDocument", "config") in views


def test_large_clouds_are_subsampled_deterministically(tmp_path):
    rng = np.random.default_rng(3)
    cloud = rng.normal(size=(5000, 3))
    written = []
    for run in range(2):
        target = tmp_path / f"run{run}.rrd"
        with make_recorder(target, max_points_per_cloud=400, max_merged_points=300) as rec:
            rec.log_raw_scans(["big"], [cloud])
            rec.log_residual_heatmap(cloud, np.abs(cloud[:, 0]))
        rrd = RecordingFile(target)
        positions = rrd.latest(["raw", "big"], "Points3D:positions")
        assert positions.shape == (400, 3)
        assert rrd.latest(["residual_heatmap", "merged"], "Points3D:positions").shape == (300, 3)
        # Every kept point is one of the input points.
        distances = np.linalg.norm(positions[:, None, :] - cloud[None, :, :], axis=2).min(1)
        assert distances.max() < 1e-5
        written.append(positions)
    np.testing.assert_array_equal(written[0], written[1])


def test_null_recorder_accepts_every_call_and_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    points, poses = _scans()
    rec = make_recorder(None)
    assert type(rec) is NullRecorder and not rec.enabled and rec.warnings == []
    with rec:
        rec.log_config({"a": 1})
        rec.log_raw_scans(NAMES, points)
        rec.log_solver_iteration(0, objective=1.0, primal_residual=0.1, dual_residual=0.1, rho=1)
        rec.log_aligned(NAMES, points, poses)
        rec.log_pair_correspondences(NAMES[0], NAMES[1], points[0], points[0])
        rec.log_residual_heatmap(points[0], np.zeros(len(points[0])))
        rec.log_ground_truth(NAMES, poses)
    rec.close()
    assert list(tmp_path.iterdir()) == []


def test_interrupted_write_leaves_no_file_and_keeps_an_old_one(tmp_path):
    points, poses = _scans()
    target = tmp_path / "recording.rrd"
    with pytest.raises(RuntimeError, match="stage failed"):
        with make_recorder(target) as rec:
            rec.log_raw_scans(NAMES, points)
            raise RuntimeError("stage failed")
    assert list(tmp_path.iterdir()) == []

    target.write_bytes(b"previous recording")
    with pytest.raises(KeyboardInterrupt):
        with make_recorder(target) as rec:
            rec.log_raw_scans(NAMES, points)
            raise KeyboardInterrupt
    assert target.read_bytes() == b"previous recording"
    assert list(tmp_path.iterdir()) == [target]


def test_rejects_mismatched_inputs(tmp_path):
    points, poses = _scans()
    with make_recorder(tmp_path / "r.rrd") as rec:
        with pytest.raises(ValueError, match="lengths differ"):
            rec.log_aligned(NAMES, points, poses[:2])
        with pytest.raises(ValueError, match=r"\(4, 4\)"):
            rec.log_aligned(NAMES[:1], points[:1], [np.eye(3)])
        with pytest.raises(ValueError, match=r"\(N, 3\)"):
            rec.log_raw_scans(["flat"], [np.zeros(10)])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="display check is Linux-only")
def test_spawn_without_display_or_viewer_warns_and_still_saves(tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(recorder_module, "find_viewer_executable", lambda: "/bin/true")

    viewer_only = make_recorder(None, spawn=True)
    assert type(viewer_only) is NullRecorder
    assert any("no display" in w for w in viewer_only.warnings)

    with make_recorder(tmp_path / "r.rrd", spawn=True) as rec:
        assert isinstance(rec, Recorder)
        assert any("no display" in w for w in rec.warnings)
        rec.log_solver_iteration(0, objective=1.0)
    assert RecordingFile(tmp_path / "r.rrd").has("solver/objective")

    monkeypatch.setattr(recorder_module, "find_viewer_executable", lambda: None)
    no_viewer = make_recorder(None, spawn=True)
    assert type(no_viewer) is NullRecorder
    assert any("no rerun viewer" in w for w in no_viewer.warnings)


def test_rerun_disabled_by_environment_gives_null_recorder(tmp_path, monkeypatch):
    monkeypatch.setenv("RERUN", "off")
    rec = make_recorder(tmp_path / "r.rrd")
    assert type(rec) is NullRecorder
    assert any("disabled" in w for w in rec.warnings)
    rec.close()
    assert list(tmp_path.iterdir()) == []


def test_colors():
    colors = scan_colors(24)
    assert colors.shape == (24, 3) and colors.dtype == np.uint8
    assert len({tuple(c) for c in colors}) == 24
    # Neighbouring scans are clearly different (L1 distance in RGB).
    assert np.abs(colors[1:].astype(int) - colors[:-1]).sum(axis=1).min() > 60
    ends = viridis(np.array([0.0, 1.0, 5.0, np.nan]), 0.0, 1.0)
    assert tuple(ends[0]) == (68, 1, 84) and tuple(ends[1]) == (253, 231, 37)
    assert tuple(ends[2]) == tuple(ends[1]) and tuple(ends[3]) == tuple(ends[1])
