"""Sequences read through KISS-ICP's own dataloaders (``sequence.dataloader``): the same
frames as a folder of files give the same trajectory; unknown names and unreadable
sources are named."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from mvreg.cli import app
from mvreg.errors import ConfigError, InputError

runner = CliRunner()


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """A synthetic LiDAR sequence as PLY files and as KITTI .bin files (x y z intensity,
    float32)."""
    from data_synth import synthesize_sequence
    from mvreg.io.loaders import load_scan_file

    root = tmp_path_factory.mktemp("seqsrc")
    synthesize_sequence(None, root / "ply", frames=60, points_per_scan=4000, seed=1)
    bins = root / "bin"
    bins.mkdir()
    for f in sorted((root / "ply").glob("*.ply")):
        pts = load_scan_file(f)[0].points.astype(np.float32)
        rows = np.column_stack([pts, np.zeros(len(pts), np.float32)])
        rows.tofile(bins / f"{f.stem}.bin")
    return root


def test_bin_frames_through_the_generic_dataloader_match_the_ply_folder(frames):
    from mvreg.io.poses import read_poses_json
    from mvreg.metrics import pose_errors
    from mvreg.sequence import register_sequence

    reg = register_sequence(frames / "bin", **{"sequence.dataloader": "generic"})
    assert len(reg.T_world_scan) == 60 and reg.all_registered
    truth = read_poses_json(frames / "ply" / "ground_truth.json")
    names = sorted(truth)
    assert sorted(reg.T_world_scan) == sorted(n.replace(".ply", "") for n in names)
    est = np.stack([reg.T_world_scan[n.replace(".ply", "")] for n in names])
    err = pose_errors(est, np.stack([truth[n] for n in names]))
    assert err.rotation_deg.max() < 0.5, err.summary()


def test_unknown_dataloader_and_unreadable_source_are_named(frames, tmp_path):
    from mvreg.sequence.sources import read_dataloader

    with pytest.raises(ConfigError, match="'kitty' is not one of .*kitti"):
        read_dataloader("kitty", frames / "bin")
    with pytest.raises(InputError, match="missing"):
        read_dataloader("generic", tmp_path / "missing")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="generic dataloader cannot read it"):
        read_dataloader("generic", empty)


def test_cli_sequence_with_a_dataloader(frames, tmp_path):
    out = tmp_path / "out"
    r = runner.invoke(
        app,
        ["register", str(frames / "bin"), "--out", str(out), "--sequence", "--no-rrd",
         "--set", "sequence.dataloader=generic", "--set", "sequence.dataloader_max_frames=12"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    import json

    poses = json.loads((out / "poses.json").read_text())["poses"]
    assert len(poses) == 12
    r = runner.invoke(
        app,
        ["register", str(frames / "bin"), "--out", str(tmp_path / "o2"), "--sequence",
         "--set", "sequence.dataloader=kitty"],
    )  # fmt: skip
    assert r.exit_code == 2 and "kitty" in r.output and "\n" not in r.output.strip()


@pytest.mark.parametrize("seed", [1, 4])
def test_a_fast_sequence_is_registered_right(tmp_path, seed):
    """22 deg per frame. Without the view tests (``sequence.view_tests``, on by default)
    odometry put frame 0 of seed 1 ~20 deg off and the ground-dominated model check
    verified it (exit 0); with every frame a view from its sensor, the free-space tests
    reject the wrong pair and every frame is placed and verified."""
    from data_synth import synthesize_sequence
    from mvreg.sequence import register_sequence

    synthesize_sequence(None, tmp_path / "fast", frames=24, points_per_scan=4000, seed=seed)
    reg = register_sequence(tmp_path / "fast")
    assert reg.all_registered, reg.report()["unverified"]
    assert reg.truth_errors["rotation_deg_max"] <= 0.2


def test_a_bad_bin_frame_is_named_and_nan_rows_are_counted(frames, tmp_path):
    import shutil

    from mvreg.sequence.sources import read_dataloader

    bins = tmp_path / "bin"
    shutil.copytree(frames / "bin", bins)
    rows = np.fromfile(bins / "scan_012.bin", dtype=np.float32).reshape(-1, 4)
    rows[:5, :3] = np.nan
    rows.tofile(bins / "scan_012.bin")
    got, names = read_dataloader("generic", bins, max_frames=14)
    assert np.isnan(got[12]).any() and names[12] == "scan_012"  # counted by the load stage
    warnings: list[str] = []
    got, _ = read_dataloader("generic", bins, max_frames=14, warnings=warnings)
    assert not np.isnan(got[12]).any() and len(got[12]) == len(rows) - 5
    assert len(warnings) == 1 and "scan_012.bin: 5 points with a NaN" in warnings[0]
    (bins / "scan_013.bin").write_bytes(b"\0" * 10)  # not a whole number of rows
    with pytest.raises(InputError, match="scan_013.bin"):
        read_dataloader("generic", bins, max_frames=14)
