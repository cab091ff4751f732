"""Georeferenced scans (issue 16): a folder far from its coordinate origin (UTM, ~1e6 m)
registers exactly like its local twin, and the outputs keep the user's frame.

The twin's coordinates are on a 2^-33 grid, so adding the offset 1e6 is exact in float64
(georeferenced files are quantized too: LAS stores integers times a scale). The load
stage then hands the pipeline the very same numbers for both folders: the poses agree
bit for bit in the local frame and to 1e-9 in the files' frame (one rounding of the
offset each way).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mvreg.cli import app
from mvreg.io.loaders import Scan, load_scans
from mvreg.io.poses import (
    pose_with_offset,
    read_poses_json,
    read_poses_kitti,
    read_poses_tum,
    write_poses_json,
)
from mvreg.pipeline.load import Loaded, local_frame_offset, to_local_frame

OFFSET = 1e6
GRID = 2.0**-33  # the spacing of float64 numbers in [2^19, 2^20): 1e6 + x is exact

runner = CliRunner()


def write_twin(
    scans: list[Scan], truth: dict, folder: Path, offset: float, grid: float | None = GRID
) -> None:
    """``scans`` quantized to ``grid`` (None: as they are), plus ``offset`` on every axis,
    as float64 .npy files with their ground truth (the same world, moved by ``offset``)."""
    folder.mkdir()
    o = np.full(3, offset)
    for s in scans:
        q = s.points if grid is None else np.round(s.points / grid) * grid
        np.save(folder / f"{Path(s.name).stem}.npy", q + o)
    write_poses_json(
        folder / "ground_truth.json",
        {f"{Path(n).stem}.npy": pose_with_offset(T, o) for n, T in truth.items()},
    )


@pytest.fixture(scope="module")
def twins(tmp_path_factory) -> tuple[Path, Path]:
    from data_synth import synthesize_scans

    tmp = tmp_path_factory.mktemp("georef")
    synthesize_scans(
        "builtin", tmp / "synth", views=6, points_per_scan=3000, seed=0, random_frames=True
    )
    scans = load_scans(tmp / "synth")
    truth = read_poses_json(tmp / "synth" / "ground_truth.json")
    write_twin(scans, truth, tmp / "local", 0.0)
    write_twin(scans, truth, tmp / "utm", OFFSET)
    write_twin(scans, truth, tmp / "utm_rounded", OFFSET, grid=None)
    return tmp / "local", tmp / "utm"


def register_cli(folder: Path, out: Path) -> dict:
    r = runner.invoke(app, ["register", str(folder), "--out", str(out), "--no-rrd", "--seed", "0"])
    assert r.exit_code == 0, r.output
    return json.loads((out / "report.json").read_text())


def read_double_ply(path: Path) -> np.ndarray:
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    assert b"property double x" in head
    n = int(head.split(b"element vertex ")[1].split(b"\n")[0])
    rec = np.frombuffer(body, dtype=[("p", "<f8", 3), ("c", "u1", 3)], count=n)
    return rec["p"]


def test_utm_offset_registers_like_its_local_twin(twins, tmp_path):
    local, utm = twins
    rep_local = register_cli(local, tmp_path / "out_local")
    rep_utm = register_cli(utm, tmp_path / "out_utm")

    assert rep_local["local_frame_offset"] is None
    assert rep_utm["local_frame_offset"] == [OFFSET] * 3
    assert rep_utm["registered"] == rep_local["registered"] == rep_local["scans"]
    # The pipeline saw the same numbers: every statistic of the run is the same (the
    # truth's translations went through the offset and back: 1e-10 apart).
    e_utm, e_local = rep_utm["ground_truth_errors"], rep_local["ground_truth_errors"]
    assert e_utm["rotation_deg"] == e_local["rotation_deg"]
    for key in ("translation", "translation_at_centroid"):
        np.testing.assert_allclose(e_utm[key], e_local[key], rtol=0, atol=1e-9)
    assert rep_utm["overlap_residual"] == rep_local["overlap_residual"]
    assert rep_utm["certificate"] == rep_local["certificate"]
    assert rep_utm["pairs"] == [
        {**p, "seconds": q["seconds"]}
        for p, q in zip(rep_local["pairs"], rep_utm["pairs"], strict=True)
    ]

    poses_local = read_poses_json(tmp_path / "out_local" / "poses.json")
    poses_utm = read_poses_json(tmp_path / "out_utm" / "poses.json")
    o = np.full(3, OFFSET)
    for name, T in poses_local.items():
        T_utm = poses_utm[name]
        # p_utm = p_local + o in every scan and in the world: T_utm = S(o) T S(-o).
        np.testing.assert_array_equal(T_utm[:3, :3], T[:3, :3])
        back = pose_with_offset(T_utm, -o)
        np.testing.assert_allclose(back, T, rtol=1e-9, atol=1e-9)
        assert np.max(np.abs(back[:3, 3] - T[:3, 3])) <= 1e-9 * max(1.0, np.abs(T[:3, 3]).max())
    kitti = read_poses_kitti(tmp_path / "out_utm" / "poses_kitti.txt")
    _, tum = read_poses_tum(tmp_path / "out_utm" / "poses_tum.txt")
    for k, T_utm in enumerate(poses_utm.values()):  # the same poses, in the files' frame
        np.testing.assert_array_equal(kitti[k], T_utm)
        np.testing.assert_allclose(tum[k], T_utm, rtol=0, atol=1e-6)

    merged_local = read_double_ply(tmp_path / "out_local" / "merged.ply")
    merged_utm = read_double_ply(tmp_path / "out_utm" / "merged.ply")
    assert merged_utm.shape == merged_local.shape
    np.testing.assert_allclose(merged_utm - OFFSET, merged_local, rtol=0, atol=1e-9)


def test_utm_offset_without_a_grid_registers_every_scan(twins):
    """The files' own rounding (1e-10 at 1e6) is all that differs from the twin: before
    the local frame, this set registered 0 of its scans."""
    from mvreg import register

    reg = register(twins[1].parent / "utm_rounded", seed=0)
    assert reg.all_registered and len(reg.T_world_scan) == 6
    assert reg.local_frame_offset.tolist() == [OFFSET] * 3
    assert reg.truth_errors["rotation_deg_max"] < 0.5
    assert reg.truth_errors["translation_at_centroid_max"] < 0.01  # object diagonal 1.4


def test_ordinary_scans_are_not_shifted(shared_data, twins):
    local, _ = twins
    for folder in (local, shared_data / "stanford_bunny_scans"):
        loaded = to_local_frame(Loaded(load_scans(folder), str(folder), None))
        assert loaded.local_frame_offset is None
        assert all(s.local_frame_offset is None for s in loaded.scans)


def test_offset_is_round_and_shifts_everything_in_float64():
    rng = np.random.default_rng(3)
    base = np.array([512_345.678, 4_123_456.789, 87.5])
    scans = [
        Scan(f"s{i}", Path(f"s{i}"), base + rng.uniform(-40, 40, size=(500, 3))) for i in range(3)
    ]
    scans[0].sensor_origin = base + 1.0
    T = np.eye(4)
    T[:3, 3] = base
    scans[1].T_world_scan_hint = T
    truth = {"s0": np.eye(4), "s1": T}
    offset = local_frame_offset(scans)
    assert offset.tolist() == [512_000.0, 4_123_000.0, 0.0]  # box diagonal ~140: to 1000
    loaded = to_local_frame(Loaded(scans, "x", truth))
    for s, old in zip(loaded.scans, scans, strict=True):
        assert s.points.dtype == np.float64
        np.testing.assert_array_equal(s.points, old.points - offset)
        assert np.abs(s.points).max() < 1000
        np.testing.assert_array_equal(s.local_frame_offset, offset)
    np.testing.assert_allclose(loaded.scans[0].sensor_origin, base + 1.0 - offset)
    # A stored pose and the truth move with the points: still map each point to the
    # same world point (minus the offset).
    p = scans[1].points[:5]
    q = loaded.scans[1].points[:5]
    H = loaded.scans[1].T_world_scan_hint
    np.testing.assert_allclose(H[:3, :3] @ q.T + H[:3, 3:4], (p + base - offset).T, atol=1e-8)
    np.testing.assert_allclose(loaded.truth["s1"], H)
    np.testing.assert_allclose(pose_with_offset(pose_with_offset(T, offset), -offset), T)
