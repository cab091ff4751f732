"""Scans that surround their sensor (a spinning LiDAR, a terrestrial laser scanner): the
sensor is found at the scan's own frame origin, the view tests see them spherically
(mvreg.pairwise.view_projection), and verification checks each scan against a bounded
model (mvreg.globalstage.scan_model.model_members). Checked against data_synth's truth."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mvreg.config import RegisterConfig
from mvreg.geometry import invert_transform, make_transform
from mvreg.globalstage.scan_model import Overlaps, model_members
from mvreg.io.loaders import load_scans
from mvreg.pairwise.preprocess import derive_scales, preprocess_all
from mvreg.pairwise.scoring import free_space_violation, unseen_violation, view_projection
from mvreg.pairwise.viewpoint import estimate_viewpoint

pytest.importorskip("trimesh")


@pytest.fixture(scope="module")
def lidar_folder(tmp_path_factory):
    """data_synth's LiDAR loop: 60 stations, 12 m range, 8000 points each."""
    from data_synth import synthesize_sequence

    folder = tmp_path_factory.mktemp("lidar")
    synthesize_sequence(None, folder, frames=60, points_per_scan=8000, max_range_m=12.0, seed=0)
    return folder


@pytest.fixture(scope="module")
def lidar(lidar_folder):
    """Five consecutive stations of the loop, preprocessed, with their true poses."""
    folder = lidar_folder
    files = sorted(folder.glob("scan_*.ply"))[:5]
    truth = json.loads((folder / "ground_truth.json").read_text())["poses"]
    scans = load_scans(files)
    cfg = RegisterConfig()
    scales = derive_scales(scans, cfg.preprocess)
    pre = preprocess_all(scans, scales.voxel, cfg.preprocess)
    T = [np.asarray(truth[s.name]) for s in scans]
    return scans, pre, T, scales, cfg


@pytest.fixture(scope="module")
def lidar_run(lidar, lidar_folder):
    """The first 28 stations of the same loop, preprocessed at the first five's voxel,
    with their true poses: more scans than one model holds (MODEL_SCANS)."""
    folder = lidar_folder
    files = sorted(folder.glob("scan_*.ply"))[:28]
    truth = json.loads((folder / "ground_truth.json").read_text())["poses"]
    scans = load_scans(files)
    _, _, _, scales, cfg = lidar
    pre = preprocess_all(scans, scales.voxel, cfg.preprocess)
    return pre, [np.asarray(truth[s.name]) for s in scans], scales.voxel


def test_a_surround_scan_is_seen_from_its_frame_origin(lidar):
    scans, pre, _, _, _ = lidar
    for s, p in zip(scans, pre, strict=True):
        c, stats = estimate_viewpoint(s.points)
        assert stats.get("origin") and np.allclose(c, 0.0)
        np.testing.assert_allclose(p.viewpoint, 0.0)
        assert view_projection(p).spherical


def test_spherical_view_tests_pass_true_poses_and_fail_wrong_ones(lidar):
    """Neighbouring stations at their true relative poses: both tests at most their
    pairwise limits (with a perspective projection the unseen test rejected most of
    them: 5 of 274 candidate pairs accepted on the 60-station set). Turned 10 deg or
    moved 0.5 m: free space above its limit even loosened by ``coarse_gate_slack`` (measured
    0.031-0.65 against 0.015; true poses 0.000)."""
    _, pre, T, scales, cfg = lidar
    a = cfg.align
    wrong = {
        "yaw 10 deg": make_transform(
            Rotation.from_euler("z", 10, degrees=True).as_matrix(), [0, 0, 0]
        ),
        "0.5 m": make_transform(np.eye(3), [0.5, 0.0, 0.0]),
        "roll 5 deg": make_transform(
            Rotation.from_euler("x", 5, degrees=True).as_matrix(), [0, 0, 0]
        ),
    }
    for i, j in ((0, 1), (1, 2), (2, 3), (3, 4), (0, 2)):
        T_i_j = invert_transform(T[i]) @ T[j]
        fs = free_space_violation(pre[i], pre[j], T_i_j, a, scales=scales)
        un = unseen_violation(pre[i], pre[j], T_i_j, a, scales=scales)
        assert fs <= a.max_free_space_violation and un <= a.max_unseen_violation, (i, j, fs, un)
        for name, W in wrong.items():
            bad = free_space_violation(pre[i], pre[j], T_i_j @ W, a, scales=scales)
            assert bad > a.coarse_gate_slack * a.max_free_space_violation, (i, j, name, bad)


def test_a_scan_is_checked_against_the_scans_covering_most_of_it(lidar):
    """With more scans than the model holds, each scan's model is the ones sharing most of
    its surface: along the loop, its nearest stations."""
    _, pre, T, scales, _ = lidar
    poses = dict(enumerate(T))
    members = model_members(pre, poses, 2.0 * scales.voxel, k=2)
    assert members[2] == [1, 3]
    assert members[0] == [1, 2]
    assert model_members(pre, poses, 2.0 * scales.voxel, k=4)[0] == [1, 2, 3, 4]


def test_searches_of_large_runs_face_only_the_scans_across():
    """Overlaps.facing bounds a search across a bridge (or around a leftover scan's
    partners) to the scans that share surface with the other side: on a chain of 40
    strips each overlapping only its neighbours, one strip on each side of the middle."""
    rng = np.random.default_rng(0)
    strips = []
    for i in range(40):  # strip i covers x in [i, i + 1.5] of a 1 m wide band
        p = rng.uniform(0.0, 1.0, (3000, 3)) * [1.5, 1.0, 0.0] + [float(i), 0.0, 0.0]
        strips.append(SimpleNamespace(points=p))
    near = Overlaps(strips, {i: np.eye(4) for i in range(40)}, 0.1)
    left, right = list(range(20)), list(range(20, 40))
    assert near.facing(left, right) == [19]
    assert near.facing(right, left) == [20]
    assert near.facing(right, [5]) == []
    assert near.facing(range(40), [7, 8], k=2) == [7, 8]  # the largest shares first
    assert near.facing(range(40), [7, 8]) == [6, 7, 8, 9]


def test_a_leftover_of_a_large_run_is_searched_near_its_pair_partner(lidar_run, monkeypatch):
    """Beyond MODEL_SCANS + 1 placed scans, a leftover scan is searched against its placed
    pair partner and the scans facing it (at most MODEL_SCANS), not against every placed
    scan: along the loop, stations near its partner."""
    from mvreg.config.align import AlignConfig
    from mvreg.globalstage import place
    from mvreg.globalstage.scan_model import MODEL_SCANS
    from mvreg.pairwise.result import PairResult

    pre, T, voxel = lidar_run
    leftover, partner = 14, 13
    known = {k: T[k] for k in range(len(T)) if k != leftover}
    assert len(known) > MODEL_SCANS + 1
    searched = []
    real = place.scan_model
    monkeypatch.setattr(
        place, "scan_model", lambda p, poses, m: searched.append(m) or real(p, poses, m)
    )
    pair = PairResult(
        i=partner, j=leftover, T_i_j=invert_transform(T[partner]) @ T[leftover],
        overlap_ratio=0.0, inlier_rmse=0.0, num_correspondences=0, fitness=0.0,
        accepted=False, reason="test",
    )  # fmt: skip
    placed = place.place_leftovers(pre, known, [leftover], voxel, AlignConfig(), results=[pair])
    assert searched and all(partner in m and len(m) <= MODEL_SCANS for m in searched)
    # Stations along the loop: the model holds its partner's neighbours, not the far end.
    assert all(max(abs(k - partner) for k in m) <= MODEL_SCANS for m in searched)
    assert all(len(m) < len(known) for m in searched)
    if leftover in placed:  # when it is placed, at its true pose
        R = placed[leftover][0][:3, :3] @ T[leftover][:3, :3].T
        assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 0.5


def test_normals_of_rings_span_the_surface(lidar):
    """With the fine level's normals from neighbourhoods spanning several rings, true poses
    of neighbouring stations fit within the noise (measured 0.95-0.96x; with one ring per
    neighbourhood 8-10x on the 60-station set, and the pairs rejected)."""
    from mvreg.pairwise.scoring import score_alignment

    _, pre, T, scales, cfg = lidar
    for i, j in ((0, 1), (1, 2), (2, 4)):
        s = score_alignment(pre[i], pre[j], invert_transform(T[i]) @ T[j], cfg.align, scales=scales)
        assert s["residual_ratio"] <= 2.0, (i, j, s["residual_ratio"])


def test_object_views_do_not_surround_their_sensor():
    """A camera looking at an object keeps its perspective view (and normals at the given
    radius): only scans with points all around their sensor are spherical."""
    from data_synth.builtin import builtin_object
    from data_synth.scans import generate_scans
    from mvreg.pairwise.view_projection import surrounds

    scans, _ = generate_scans(
        builtin_object(0, subdivisions=4), views=4, seed=0, points_per_scan=2000
    )
    for s in scans:
        c, _ = estimate_viewpoint(s.points)
        assert c is not None and not surrounds(s.points, c)


def _yaw(deg: float) -> np.ndarray:
    return make_transform(Rotation.from_euler("z", deg, degrees=True).as_matrix(), np.zeros(3))


def _pair(i, j, T_i_j):
    from mvreg.pairwise.result import PairResult

    return PairResult(
        i=i, j=j, T_i_j=T_i_j, overlap_ratio=0.3, inlier_rmse=0.0, num_correspondences=500,
        fitness=0.3, accepted=True, reason="",
    )  # fmt: skip


def test_stations_fitting_the_rest_on_ground_alone_are_not_verified(lidar_run):
    """Two neighbouring stations hung on the rest by one wrong pair, put as one 10 m
    outward of station 3 and turned 140 deg (on the 60-station scene a street's repeated
    scenery matched such a pair): their objects lie beyond the others' range, so both
    free-space tests pass, and their ground fits the others' ground (overlap 0.65 with the
    scans placed without them). Nothing but that plane holds them, so they are not
    verified (mvreg.globalstage.probes.on_one_plane; before it, both were, by the model
    check). The stations closing cycles are; so are the same two at their true poses,
    hung by the true pair on their neighbours."""
    from mvreg.config.align import AlignConfig
    from mvreg.globalstage.verify import verify_scans

    pre, T, voxel = lidar_run
    rest, hung = list(range(9)), [20, 21]
    centre = np.mean([t[:3, 3] for t in T], axis=0)
    out = T[3][:3, 3] - centre
    out[2] = 0.0
    at = T[3] @ make_transform(np.eye(3), T[3][:3, :3].T @ (10.0 * out / np.linalg.norm(out)))
    move = at @ _yaw(140.0) @ invert_transform(T[20])
    for poses, bridge in (
        ({k: T[k] for k in rest} | {k: move @ T[k] for k in hung}, (3, 20)),
        ({k: T[k] for k in range(16, 22)}, (19, 20)),
    ):
        base = [k for k in poses if k not in hung]
        chain = [(a, b) for a in base for b in base if 0 < b - a <= 2] + [(20, 21), bridge]
        results = [_pair(a, b, invert_transform(poses[a]) @ poses[b]) for a, b in chain]
        weights = dict.fromkeys(chain, 1.0)
        ver = verify_scans(pre, results, weights, poses, voxel, AlignConfig(), discrete=False)
        assert all(ver[k].status == "verified" for k in base)
        if bridge == (3, 20):
            for k in hung:
                assert ver[k].status == "unverified", (k, ver[k].evidence)
                assert "lie off one plane" in ver[k].reason, ver[k].reason
        else:
            assert all(ver[k].status == "verified" for k in hung), {k: ver[k].reason for k in hung}


def test_a_leftover_is_not_placed_on_ground_alone(lidar_run):
    """Station 20 left over, with a pair hypothesis (the kind a street's repeated scenery
    gives) that puts it 10 m outward of station 3, turned 140 deg, and only stations
    0-8 placed: none of its true neighbours is, so any placement is wrong. There its
    ground fits theirs and its objects lie beyond their range; the placement's checks
    refuse it (mvreg.globalstage.probes.on_one_plane), and no other pose passes."""
    from mvreg.config.align import AlignConfig
    from mvreg.globalstage.place import LeftoverSearches, place_leftovers

    pre, T, voxel = lidar_run
    rest, s = list(range(9)), 20
    centre = np.mean([t[:3, 3] for t in T], axis=0)
    out = T[3][:3, 3] - centre
    out[2] = 0.0
    at = T[3] @ make_transform(np.eye(3), T[3][:3, :3].T @ (10.0 * out / np.linalg.norm(out)))
    wrong = at @ _yaw(140.0)
    pair = _pair(3, s, invert_transform(T[3]) @ wrong)
    known = {k: T[k] for k in rest}
    record = LeftoverSearches()
    placed = place_leftovers(pre, known, [s], voxel, AlignConfig(), [pair], searched=record)
    assert s not in placed
    # Recorded as searched in vain from this start against these stations: a second pass
    # does not search it again unless that changes.
    assert record.failed[s] == (LeftoverSearches.key(s, [pair]), frozenset(known))


def test_a_pair_fitting_on_the_ground_alone_is_not_accepted(lidar_run):
    """The acceptance rule asks a pair's close matches to hold its heading and slide
    (mvreg.pairwise.scoring.off_plane_matches): station 20 put 10 m outward of station 3
    and turned 140 deg meets it on the ground alone (none of its matches off that plane)
    and is rejected for it; chain neighbours at their true poses hold many more and pass."""
    from mvreg.config.align import AlignConfig
    from mvreg.pairwise.decision import decide
    from mvreg.pairwise.icp import coarse_icp
    from mvreg.pairwise.scoring import PAIR_OFF_PLANE_MATCHES, score_alignment

    pre, T, voxel = lidar_run
    cfg = AlignConfig()
    for i, j in ((3, 4), (10, 11), (20, 21)):
        scores = score_alignment(pre[i], pre[j], invert_transform(T[i]) @ T[j], cfg)
        assert scores["off_plane_matches"] >= 3 * PAIR_OFF_PLANE_MATCHES, (i, j, scores)
        assert decide(scores, cfg) == "", (i, j, decide(scores, cfg))
    centre = np.mean([t[:3, 3] for t in T], axis=0)
    out = T[3][:3, 3] - centre
    out[2] = 0.0
    at = T[3] @ make_transform(np.eye(3), T[3][:3, :3].T @ (10.0 * out / np.linalg.norm(out)))
    T_3_20 = coarse_icp(pre[3], pre[20], invert_transform(T[3]) @ at @ _yaw(140.0), cfg, voxel)
    scores = score_alignment(pre[3], pre[20], T_3_20, cfg)
    assert scores["overlap_ratio"] >= cfg.min_overlap_ratio  # the ground coincides
    assert scores["off_plane_matches"] < PAIR_OFF_PLANE_MATCHES, scores
    assert "one plane" in decide(scores, cfg)


def test_true_neighbours_read_no_free_space_between_the_rings(lidar_folder):
    """A spherical view's front depth per cell comes from its samples and those of the
    cells around (mvreg.pairwise.scoring.depth_grid), so from up to two cells away; the
    depth slack allows for that. With one cell's slack, stations 7-9 and 28-29 of the
    loop at 10k points a scan (the scale benchmark's scene, voxel from all 60) read 0.023
    and 0.020 at their true poses, 4-5x the limit, and were rejected; ground points between
    two rings of the other scan, whose normals (from one ring) are tilted towards the
    sensor. Turned or moved poses still read far above the limit."""
    from data_synth import synthesize_sequence
    from mvreg.pairwise import with_noise

    folder = lidar_folder.parent / "lidar10k"
    synthesize_sequence(None, folder, frames=60, points_per_scan=10000, max_range_m=12.0, seed=0)
    files = sorted(folder.glob("scan_*.ply"))
    truth = json.loads((folder / "ground_truth.json").read_text())["poses"]
    cfg = RegisterConfig()
    a = cfg.align
    scales = derive_scales(load_scans(files), cfg.preprocess)
    scans = load_scans([files[k] for k in (7, 9, 28, 29)])
    pre = preprocess_all(scans, scales.voxel, cfg.preprocess)
    scales = with_noise(scales, pre)
    T = [np.asarray(truth[s.name]) for s in scans]
    assert scales.voxel == pytest.approx(0.172, abs=0.002)
    for i, j in ((0, 1), (2, 3)):
        T_i_j = invert_transform(T[i]) @ T[j]
        fs = free_space_violation(pre[i], pre[j], T_i_j, a, scales=scales)
        assert fs <= a.max_free_space_violation, (i, j, fs)
        for W in (_yaw(10.0), make_transform(np.eye(3), [0.5, 0.0, 0.0])):
            bad = free_space_violation(pre[i], pre[j], T_i_j @ W, a, scales=scales)
            assert bad > a.coarse_gate_slack * a.max_free_space_violation, (i, j, bad)
