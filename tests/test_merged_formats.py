"""Merged output as LAZ or E57 (``output.merged_format``): every point of every registered
scan, one scan per input with its pose, read back with laspy and pye57 and checked against
the scan files and poses.json."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mvreg.config.align import AlignConfig
from mvreg.geometry import transform_points


@pytest.fixture(scope="module")
def registered(tmp_path_factory):
    from data_synth import synthesize_scans
    from mvreg import register

    folder = tmp_path_factory.mktemp("mf") / "scans"
    synthesize_scans(
        "builtin", folder, views=6, noise=0.002, seed=5, random_frames=True, points_per_scan=3000
    )
    reg = register(folder, seed=0)
    assert len(reg.T_world_scan) >= 3, reg.report()["verification"]
    return folder, reg


def _write(reg, fmt, out):
    from mvreg.io.writers import write_registration

    reg.config.output.merged_format = fmt
    try:
        return write_registration(reg, out)
    finally:
        reg.config.output.merged_format = "ply"


def _file_points(folder, name):
    from mvreg.io.loaders import load_scan_file

    return load_scan_file(folder / name)[0].points


def test_laz_holds_every_point_in_the_world_frame_with_one_source_id_per_scan(registered, tmp_path):
    import laspy

    folder, reg = registered
    paths = _write(reg, "laz", tmp_path)
    assert paths["merged_laz"] == tmp_path / "merged.laz"
    poses = json.loads((tmp_path / "poses.json").read_text())["poses"]
    las = laspy.read(tmp_path / "merged.laz")
    vlr = next(v for v in las.header.vlrs if v.user_id == "mvreg")
    listed = json.loads(vlr.record_data)["scans"]
    assert [s["name"] for s in listed] == list(poses)
    xyz = np.column_stack([las.x, las.y, las.z])
    scale = float(las.header.scales[0])
    assert scale <= reg.scales.fine_voxel / 100
    for k, s in enumerate(listed):
        assert np.allclose(s["T_world_scan"], poses[s["name"]], atol=1e-15)
        mine = xyz[np.asarray(las.point_source_id) == k]
        want = transform_points(np.asarray(poses[s["name"]]), _file_points(folder, s["name"]))
        assert mine.shape == want.shape
        assert np.max(np.abs(mine - want)) <= scale  # quantized to the LAS scale


def test_e57_holds_each_scan_in_its_own_frame_with_its_pose(registered, tmp_path):
    import pye57

    folder, reg = registered
    _write(reg, "e57", tmp_path)
    poses = json.loads((tmp_path / "poses.json").read_text())["poses"]
    e57 = pye57.E57(str(tmp_path / "merged.e57"))
    assert e57.scan_count == len(poses)
    for k, (name, T) in enumerate(poses.items()):
        h = e57.get_header(k)
        assert h["name"].value() == name
        assert np.allclose(h.rotation_matrix, np.asarray(T)[:3, :3], atol=1e-12)
        assert np.allclose(h.translation, np.asarray(T)[:3, 3], atol=1e-12)
        data = e57.read_scan_raw(k)
        pts = np.column_stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]])
        want = _file_points(folder, name)
        assert np.max(np.abs(pts - want)) <= np.max(np.abs(want)) * 2.0**-23  # float32


def test_ply_only_by_default_and_the_format_is_checked(registered, tmp_path):
    from mvreg.config import load_config
    from mvreg.errors import ConfigError

    _, reg = registered
    paths = _write(reg, "ply", tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in paths.values())
    assert not (tmp_path / "merged.laz").exists() and not (tmp_path / "merged.e57").exists()
    with pytest.raises((ConfigError, ValueError), match="merged_format"):
        load_config(**{"output.merged_format": "las"})


def test_georeferenced_scans_keep_their_precision_in_e57():
    """Coordinates ~1e6 in single precision would round by ~0.06: the stored points are
    shifted by their rounded centroid and the pose takes the shift (same world points)."""
    from mvreg.io.merged_formats import fit_single_precision

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3)) + np.array([4.5e5, 5.2e6, 300.0])
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    T2, stored = fit_single_precision(T, pts, fine_voxel=0.01)
    assert np.max(np.abs(stored)) < 10
    back = transform_points(T2, stored.astype(np.float32).astype(np.float64))
    assert np.max(np.abs(back - transform_points(T, pts))) < 1e-4  # << fine voxel / 100
    assert fit_single_precision(T, pts - pts.mean(axis=0), 0.01)[0] is T  # local: as is


def test_a_merged_e57_registers_again_and_its_stored_poses_are_reported(registered, tmp_path):
    """merged.e57 is a multi-scan E57 with stored poses: registering it again reports how
    far the new poses are from the stored ones (gauge-free), here the same registration."""
    from mvreg import register

    _, reg = registered
    _write(reg, "e57", tmp_path / "first")
    again = tmp_path / "again"
    again.mkdir()
    (tmp_path / "first" / "merged.e57").rename(again / "merged.e57")
    reg2 = register(again, seed=0)
    d = reg2.report()["stored_pose_differences"]
    assert d is not None and len(d["scans"]) == len(reg2.T_world_scan) >= 3
    assert d["rotation_deg_max"] < 0.1, d
    assert max(d["translation_at_centroid"]) < reg.scales.fine_voxel, d
    assert reg.report()["stored_pose_differences"] is None  # PLY files store no pose


def test_stored_poses_are_a_second_chance_for_pairs_features_miss(registered):
    """Every pair marked rejected by the features: the stored poses (here the truth, as an
    E57 scanner pose would be) give each an ICP start, and the acceptance rule keeps those
    that fit, near the truth; a stored pose turned 90 deg is a hint, not
    trusted: none of that scan's pairs is accepted at the turned pose."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    from mvreg.io.loaders import load_scan_file
    from mvreg.pairwise import PairResult, derive_scales, preprocess_all, with_noise
    from mvreg.pairwise.stored_poses import retry_from_stored_poses

    folder, _ = registered
    truth = json.loads((folder / "ground_truth.json").read_text())["poses"]
    names = sorted(truth)
    scans = [load_scan_file(folder / n)[0] for n in names]
    scales = derive_scales(scans)
    pre = preprocess_all(scans, scales.voxel)
    scales = with_noise(scales, pre)
    T = [np.asarray(truth[n]) for n in names]
    rejected = [
        PairResult(i=i, j=j, T_i_j=np.eye(4), overlap_ratio=0.0, inlier_rmse=np.inf,
                   num_correspondences=0, fitness=0.0, accepted=False, reason="features")
        for i in range(len(scans)) for j in range(i + 1, len(scans))
    ]  # fmt: skip

    def angle(A, B):
        return np.degrees(Rotation.from_matrix(A[:3, :3].T @ B[:3, :3]).magnitude())

    hinted = [replace(s, T_world_scan_hint=T[k]) for k, s in enumerate(scans)]
    out = retry_from_stored_poses(pre, hinted, rejected, AlignConfig(), scales)
    accepted = [r for r in out if r.accepted]
    assert len(accepted) >= 6, [r.reason for r in out]
    errors = [angle(r.T_i_j, np.linalg.inv(T[r.i]) @ T[r.j]) for r in accepted]
    assert all(r.stats["init"] == "stored poses" for r in accepted)
    # Pairwise ICP on a small overlap slides a little (0-2: overlap 0.23, 1.8 deg); the
    # global stage reconciles. None is a wrong pose.
    assert np.median(errors) < 0.5 and max(errors) < 3.0, np.round(errors, 2)
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    hinted[0] = replace(hinted[0], T_world_scan_hint=T[0] @ turn)
    out = retry_from_stored_poses(pre, hinted, rejected, AlignConfig(), scales)
    for r in out:
        if r.accepted and 0 in (r.i, r.j):
            assert angle(r.T_i_j, np.linalg.inv(T[r.i]) @ T[r.j]) < 3.0  # not the turned one
    assert sum(r.accepted for r in out) >= len(accepted) - (len(scans) - 1)
