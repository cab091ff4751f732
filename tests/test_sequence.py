"""Ordered LiDAR sequences: KISS-ICP odometry, loop closures, global solve (issue 4).

The main fixture is a closed loop of 36 sparse scans (about 4,000 points, 10 degrees of
turn between scans) through a synthetic scene with a ground plane: KISS-ICP loses track
on it (the ground rings look alike from scan to scan), so the test also shows that the
verified pairs recover what the odometry missed. A scene without ground, where KISS-ICP
does track, checks the odometry itself.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import open3d as o3d
import pytest

from data_synth import synthesize_sequence
from mvreg.errors import ConfigError, InputError
from mvreg.geometry import invert_transform, rotation_angle_deg
from mvreg.io.loaders import list_scan_files, load_scan
from mvreg.sequence import (
    SequenceRegistration,
    find_gaps,
    kiss_icp_odometry,
    read_timestamps_file,
    register_sequence,
    timestamps_from_names,
)

LOOP = dict(frames=36, points_per_scan=4000, seed=3)


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    return synthesize_sequence(None, tmp_path_factory.mktemp("loop"), **LOOP)


@pytest.fixture(scope="module")
def loop_registration(loop) -> SequenceRegistration:
    return register_sequence(loop.out_dir)


def _loop_diameter(truth: dict) -> float:
    p = np.array([T[:3, 3] for T in truth.values()])
    return float(np.linalg.norm(p.max(0) - p.min(0)))


def test_closed_loop_registered_within_bounds(loop, loop_registration):
    reg = loop_registration
    assert reg.unregistered == []
    assert len(reg.T_world_scan) == 36
    err = reg.truth_errors
    # Measured: rotation max 0.20 deg, position max 0.035 m on a 30 m loop (77 m path).
    assert err["rotation_deg_max"] < 0.5
    assert err["rotation_deg_median"] < 0.15
    assert err["translation_max"] < 0.003 * _loop_diameter(loop.T_world_scan)
    assert reg.solve.certified
    pairs = reg.sequence["pairs_by_kind"]
    assert pairs["sequential"]["accepted"] == pairs["sequential"]["tried"] == 69
    assert reg.sequence["loop_closures"]["accepted"] >= 3


def test_drift_of_the_odometry_is_removed(loop_registration):
    drift = loop_registration.sequence["drift"]
    assert drift["closed_loop"]
    assert drift["loop_pair"] == ["scan_000.ply", "scan_035.ply"]
    # KISS-ICP alone: 1.76 m end-to-start (it stalls on these scans); measured 0.015 m after.
    odo, fin = drift["odometry_end_to_start_vs_truth"], drift["global_end_to_start_vs_truth"]
    assert odo > 0.5
    assert fin < 0.001 * drift["truth_path_length"]
    assert fin * 5 < odo
    assert drift["global_end_to_start_rotation_deg_vs_truth"] < 0.3
    # Without the truth: the same error seen through the verified loop closure.
    assert drift["global_end_to_start_vs_loop_closure"] < 0.05
    assert drift["odometry_end_to_start_vs_loop_closure"] > 0.5


def test_report_holds_timestamps_odometry_and_is_json(loop_registration):
    reg = loop_registration
    report = json.loads(json.dumps(reg.report()))
    seq = report["sequence"]
    assert seq["timestamp_source"] == "timestamps.txt"
    assert seq["gaps"] == [] and seq["warnings"] == []
    times = np.array([reg.timestamps[f"scan_{k:03d}.ply"] for k in range(36)])
    np.testing.assert_allclose(times, np.arange(36) / 10.0)
    assert seq["odometry"]["backend"] == "kiss-icp"
    assert seq["odometry"]["config"]["data"]["deskew"] is False
    # KISS-ICP's settings come from the data: voxel = max range / 100.
    assert seq["odometry"]["voxel_size"] == pytest.approx(seq["odometry"]["max_range"] / 100)
    assert set(reg.T_odom_scan) == set(reg.scan_names)
    assert {p["kind"] for p in report["pairs"]} == {"sequential", "loop"}


def test_missing_and_broken_scans_are_bridged_or_reported(loop, tmp_path):
    folder = tmp_path / "gappy"
    shutil.copytree(loop.out_dir, folder)
    (folder / "scan_017.ply").unlink()  # a gap: timestamps.txt no longer matches
    rng = np.random.default_rng(0)
    noise = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.uniform(-20.0, 20.0, (4000, 3))))
    o3d.io.write_point_cloud(str(folder / "scan_025.ply"), noise)  # overlaps nothing
    reg = register_sequence(folder)
    seq = reg.sequence
    assert seq["timestamp_source"] == "file names"
    assert any("timestamps.txt" in w for w in seq["warnings"])
    assert seq["gaps"] == [
        {
            "after": "scan_016.ply",
            "before": "scan_018.ply",
            "time_step": 2.0,
            "median_time_step": 1.0,
            "missing_scans": 1,
        }
    ]
    # The broken scan gets no pose; the scans across the gap are registered.
    assert reg.unregistered == ["scan_025.ply"]
    assert "scan_025.ply" not in reg.T_world_scan
    assert {"scan_016.ply", "scan_018.ply"} <= set(reg.T_world_scan)
    err = reg.truth_errors
    assert "scan_025.ply" not in err["scans"]
    assert err["rotation_deg_max"] < 0.5
    assert err["translation_max"] < 0.003 * _loop_diameter(loop.T_world_scan)


def test_point_arrays_with_given_timestamps(loop):
    files = list_scan_files(loop.out_dir)[:10]
    points = [load_scan(f).points for f in files]
    times = 100.0 + 0.1 * np.arange(10)
    truth = {f"s{k}": loop.T_world_scan[f.name] for k, f in enumerate(files)}
    reg = register_sequence(
        points, names=[f"s{k}" for k in range(10)], timestamps=times, truth=truth
    )
    assert reg.unregistered == []
    assert reg.sequence["timestamp_source"] == "given"
    assert not reg.sequence["drift"]["closed_loop"]  # a stretch of the loop, no revisit
    assert reg.sequence["loop_closures"]["candidates"] == 0
    assert reg.truth_errors["rotation_deg_max"] < 0.3
    assert reg.truth_errors["translation_max"] < 0.05


def test_kiss_icp_odometry_tracks_a_structured_scene(tmp_path):
    # Without the ground plane, walls and objects fill the scans and KISS-ICP tracks
    # 40 sparse scans (measured: 0.28 m worst position, 0.05 m at the end, 78 m path).
    seq = synthesize_sequence(None, tmp_path, frames=40, points_per_scan=3000, seed=3, ground=False)
    scans = [load_scan(p) for p in seq.scan_paths]
    odom = kiss_icp_odometry([s.points for s in scans], seq.timestamps_s)
    truth = np.stack([seq.T_world_scan[s.name] for s in scans])
    rel_true = np.einsum("ij,mjk->mik", invert_transform(truth[0]), truth)
    err = np.einsum("mji,mjk->mik", rel_true[:, :3, :3], odom.T_odom_scan[:, :3, :3])
    path = np.sum(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1))
    position = np.linalg.norm(odom.T_odom_scan[:, :3, 3] - rel_true[:, :3, 3], axis=1)
    assert np.allclose(odom.T_odom_scan[0], np.eye(4))
    assert position.max() < 0.01 * path
    assert rotation_angle_deg(err).max() < 2.0
    assert odom.voxel_size == pytest.approx(odom.max_range / 100)


# ---------------------------------------------------------------------------- timestamps


def test_timestamps_from_file_names():
    np.testing.assert_array_equal(
        timestamps_from_names(["scan_000.ply", "scan_002.ply", "scan_10.pcd"]), [0, 2, 10]
    )
    np.testing.assert_allclose(
        timestamps_from_names(["1317357625.557814.pcd", "1317357625.657814.pcd"]),
        [1317357625.557814, 1317357625.657814],
    )
    assert timestamps_from_names(["a.ply", "b.ply"]) is None  # no numbers
    assert timestamps_from_names(["scan_5.ply", "scan_3.ply"]) is None  # not increasing


def test_timestamps_file_formats(tmp_path):
    names = ["a.ply", "b.ply", "c.ply"]
    path = tmp_path / "timestamps.txt"
    path.write_text("# seconds\n0.5\n0.6\n0.8\n")
    np.testing.assert_allclose(read_timestamps_file(path, names), [0.5, 0.6, 0.8])
    path.write_text("c.ply 3.0\nold.ply 0.1\na.ply 1.0\nb.ply 2.0\n")  # any order, extras ok
    np.testing.assert_allclose(read_timestamps_file(path, names), [1.0, 2.0, 3.0])
    path.write_text("0.5\n0.6\n")  # one per line, but not one per scan
    assert read_timestamps_file(path, names) is None
    path.write_text("a.ply 1.0\nc.ply 3.0\n")
    with pytest.raises(InputError, match="no time for 1 scan"):
        read_timestamps_file(path, names)
    path.write_text("0.5\n0.4\n0.8\n")
    with pytest.raises(InputError, match="increase"):
        read_timestamps_file(path, names)
    path.write_text("0.5\nnoon\n0.8\n")
    with pytest.raises(InputError, match="not a number"):
        read_timestamps_file(path, names)


def test_gaps_are_steps_well_above_the_median():
    gaps = find_gaps(np.array([0.0, 0.1, 0.2, 0.5, 0.6, 0.7]), gap_factor=1.5)
    assert [(g["after"], g["missing_scans"]) for g in gaps] == [(2, 2)]
    assert gaps[0]["time_step"] == pytest.approx(0.3)
    assert find_gaps(np.arange(5.0), 1.5) == []


def test_bad_input_and_settings(tmp_path):
    with pytest.raises(InputError):
        register_sequence([np.zeros((500, 3))])  # one scan
    with pytest.raises(InputError):
        register_sequence(
            [np.random.default_rng(0).normal(size=(500, 3))] * 3, timestamps=[0.0, 1.0, 1.0]
        )
    with pytest.raises(ConfigError, match="sequence.gap_factor"):
        register_sequence(tmp_path, **{"sequence.gap_factor": 0.5})


def test_sequence_tracks_keep_their_normal_agreement_unless_given():
    """register's tracks default to 0.9; sequences keep 0.7 unless tracks.min_normal_cos
    is given (LiDAR normals are noisier)."""
    from mvreg.config import SequenceConfig, load_config
    from mvreg.sequence import sequence_tracks_config

    cfg = load_config()
    assert cfg.tracks.min_normal_cos == 0.9
    assert sequence_tracks_config(cfg.tracks, SequenceConfig()).min_normal_cos == 0.7
    given = load_config(**{"tracks.min_normal_cos": 0.8})
    assert sequence_tracks_config(given.tracks, SequenceConfig()).min_normal_cos == 0.8
    assert sequence_tracks_config(cfg.tracks, SequenceConfig()).max_correspondences_per_pair == 400


def test_cli_sequence_with_ground_truth_in_the_folder(loop, tmp_path):
    """Issue 16: `register --sequence` on `mvreg synth --sequence` output (ground_truth.json
    beside the scans) used to exit 4 (KeyError 'translation_at_centroid_max') after
    writing its files; the summary and the report now carry the same errors as register."""
    import json

    from typer.testing import CliRunner

    from mvreg.cli import app

    out = tmp_path / "out"
    res = CliRunner().invoke(
        app, ["register", str(loop.out_dir), "--out", str(out), "--sequence", "--no-rrd"]
    )
    assert res.exit_code in (0, 3), res.output
    report = json.loads((out / "report.json").read_text())
    e = report["ground_truth_errors"]
    assert e["translation_at_centroid_max"] >= 0 and e["rotation_deg_max"] < 0.5
    assert "sequence" in report and report["sequence"]["drift"]["closed_loop"] in (True, False)
