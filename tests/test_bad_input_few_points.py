"""A scan with fewer than ``min_points`` points (issue 16): left out and listed as
unregistered with the reason, the others registered (exit 3, a partial result); the old
error (exit 2) only when fewer than 2 usable scans remain."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mvreg.cli import app
from mvreg.errors import ScanFileError
from mvreg.io.loaders import TooFewPointsError, load_scan
from mvreg.pipeline import NoProgress, load_source
from tests.test_bad_input import GOOD, ascii_rows, ply_with, register_args

runner = CliRunner()


@pytest.fixture(scope="module")
def builtin_with_tiny(tmp_path_factory) -> Path:
    """Six synthetic views of the built-in object and ``tiny.npy``: 50 of their points."""
    from data_synth import synthesize_scans

    d = tmp_path_factory.mktemp("few") / "scans"
    synthesize_scans("builtin", d, views=6, points_per_scan=3000, seed=0, random_frames=True)
    np.save(d / "tiny.npy", load_scan(d / "scan_002.ply").points[:50])
    return d


def test_tiny_scan_is_unregistered_and_the_others_registered(builtin_with_tiny, tmp_path):
    r = runner.invoke(app, register_args(tmp_path, builtin_with_tiny, "--seed", "0"))
    assert r.exit_code == 3, r.output  # partial: not every scan is placed
    assert "Traceback" not in r.output
    assert "tiny.npy: not registered: only 50 valid points" in r.output
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["unregistered"] == ["tiny.npy"]
    assert report["registered"] == [f"scan_{i:03d}.ply" for i in range(6)]
    assert "tiny.npy" in report["scans"]
    assert report["skipped_files"] == []
    why = report["verification"]["scans"]["tiny.npy"]
    assert why["status"] == "unregistered"
    assert why["reason"] == "only 50 valid points, fewer than the minimum of 100 (min_points)"
    assert report["rejected_scans"] == [
        {"file": "tiny.npy", "reason": why["reason"], "scan": "tiny.npy"}
    ]
    poses = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert sorted(poses["poses"]) == report["registered"]
    assert poses["unregistered"] == ["tiny.npy"]
    assert report["ground_truth_errors"]["rotation_deg_max"] < 1.0


def test_one_usable_scan_left_is_still_an_error(tmp_path):
    d = tmp_path / "scans"
    d.mkdir()
    np.save(d / "a.npy", GOOD)
    (d / "few.ply").write_bytes(ply_with(ascii_rows(20)))
    r = runner.invoke(app, register_args(tmp_path, d))
    assert r.exit_code == 2, r.output
    assert "needs at least 2 scans, found 1 (1 more with fewer than min_points = " in r.output
    assert " points: few.ply)" in r.output
    assert not (tmp_path / "out" / "poses.json").exists()


def test_too_few_points_after_far_strays_is_left_out_too(tmp_path):
    d = tmp_path / "scans"
    d.mkdir()
    np.save(d / "a.npy", GOOD)
    np.save(d / "b.npy", GOOD + 0.5)
    strays = GOOD[:150].copy()
    strays[:60] += 1e9  # 90 points left once the strays are dropped
    np.save(d / "c.npy", strays)
    loaded = load_source(d, None, 100, None, None, NoProgress())
    assert [s.name for s in loaded.scans] == ["a.npy", "b.npy"]
    (entry,) = loaded.skipped
    assert entry["scan"] == "c.npy"
    assert "only 90 points away from far strays" in entry["reason"]


def test_a_single_small_scan_still_raises(tmp_path):
    np.save(tmp_path / "few.npy", GOOD[:20])
    with pytest.raises(TooFewPointsError, match="only 20 valid points") as e:
        load_scan(tmp_path / "few.npy")
    assert isinstance(e.value, ScanFileError) and e.value.exit_code == 2
