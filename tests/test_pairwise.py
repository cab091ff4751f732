"""Stages 1-4: preprocess, candidate pairs, pairwise alignment, correspondences, tracks.

Accuracy is checked against known poses: synthetic views of the built-in object (always
run) and the real Stanford bunny scans against ``bun.conf`` (when ../shared is present).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mvreg.config import AlignConfig, PairsConfig, PreprocessConfig, TracksConfig
from mvreg.geometry import invert_transform, make_transform, rotation_angle_deg, transform_points
from mvreg.io.loaders import Scan, load_scans
from mvreg.pairwise import (
    align_pair,
    align_pairs,
    build_tracks,
    candidate_pairs,
    derive_voxel_size,
    mutual_correspondences,
    resample,
    score_alignment,
    tracks_from_correspondences,
)
from mvreg.pairwise.align import reject_relative_outliers
from mvreg.pairwise.preprocess import (
    outlier_mask,
    preprocess,
    single_view_axis,
    view_axis_occlusion,
    view_direction,
)
from mvreg.pairwise.result import PairResult, pair_seed
from mvreg.pairwise.scoring import free_space_violation, unseen_violation

# ----------------------------------------------------------------------------- helpers


def relative_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation degrees, translation distance) between two transforms."""
    delta = invert_transform(T_true) @ T_est
    return float(rotation_angle_deg(delta[:3, :3])), float(
        np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])
    )


def view_scan(points, normals, direction, T_local_world, name, noise=0.0, seed=0) -> Scan:
    """Points of a surface sample facing ``direction``, in a local frame."""
    direction = np.asarray(direction, float) / np.linalg.norm(direction)
    keep = normals @ direction > 0.15
    local = transform_points(T_local_world, points[keep])
    if noise:
        local = local + np.random.default_rng(seed).normal(scale=noise, size=local.shape)
    return Scan(name=name, path=Path(name), points=local)


@pytest.fixture(scope="module")
def synthetic():
    """Views of the built-in object (size 1) in random local frames, with their poses."""
    trimesh = pytest.importorskip("trimesh")
    from data_synth.builtin import builtin_object

    mesh = builtin_object(0, subdivisions=5)
    points, faces = trimesh.sample.sample_surface(mesh, 60000, seed=3)
    normals = np.asarray(mesh.face_normals)[faces]
    rng = np.random.default_rng(7)
    directions = {"front": [1, 0, 0.2], "side": [0.6, 0.8, 0.1], "back": [-1, 0, -0.2]}
    scans, T_world_local, view_dirs = [], [], []
    for k, (name, d) in enumerate(directions.items()):
        R = Rotation.random(random_state=rng).as_matrix()
        T_local_world = make_transform(R, rng.normal(scale=2.0, size=3))
        scans.append(view_scan(points, normals, d, T_local_world, f"{name}.npy", 1e-4, k))
        T_world_local.append(invert_transform(T_local_world))
        view_dirs.append(R @ (np.asarray(d, float) / np.linalg.norm(d)))  # in the local frame
    return scans, T_world_local, mesh, view_dirs


@pytest.fixture(scope="module")
def synthetic_pre(synthetic):
    scans, T_world_local = synthetic[:2]
    voxel = derive_voxel_size(scans)
    return [preprocess(s, voxel) for s in scans], T_world_local


# ----------------------------------------------------------------------------- preprocess


def test_voxel_size_follows_the_data_and_its_units(synthetic):
    scans = synthetic[0]
    voxel = derive_voxel_size(scans)
    counts = [len(preprocess(s, voxel).points) for s in scans]
    assert 1000 < np.median(counts) < 3000  # target 2000 points per scan
    in_mm = [Scan(s.name, s.path, s.points * 1000.0) for s in scans]
    assert derive_voxel_size(in_mm) == pytest.approx(1000.0 * voxel, rel=0.02)
    assert derive_voxel_size(scans, PreprocessConfig(voxel_size=0.5)) == 0.5
    dense = derive_voxel_size(scans, PreprocessConfig(target_points_per_scan=8000))
    assert dense < 0.7 * voxel


def test_normals_are_consistent_and_outward(synthetic, synthetic_pre):
    scans, T_world_local, mesh = synthetic[:3]
    pre, _ = synthetic_pre
    tree = cKDTree(mesh.triangles_center)
    for p, T in zip(pre, T_world_local, strict=True):
        assert p.orientation == "outward"
        for pts, nrm in ((p.points, p.normals), (p.fine_points, p.fine_normals)):
            world_n = nrm @ T[:3, :3].T
            _, face = tree.query(transform_points(T, pts))
            agree = np.einsum("ij,ij->i", world_n, mesh.face_normals[face]) > 0
            assert agree.mean() > 0.97, p.name
            np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-9)
        assert p.features.shape == (len(p.points), 33)
        assert 0 < p.noise < 0.1 * p.fine_voxel_size


def test_normals_follow_file_normals_and_sensor_origin(synthetic):
    scan = synthetic[0][0]
    voxel = derive_voxel_size([scan])
    outward = preprocess(scan, voxel)
    # Inverted normals stored in the file win over the outward guess.
    _, idx = cKDTree(outward.fine_points).query(scan.points)
    flipped = Scan(scan.name, scan.path, scan.points, normals=-outward.fine_normals[idx])
    pre = preprocess(flipped, voxel)
    assert pre.orientation == "file normals"
    assert np.mean(np.einsum("ij,ij->i", pre.normals, outward.normals) < 0) > 0.99
    # A sensor origin behind the surface, as a file could record it, is obeyed too.
    centroid = scan.points.mean(axis=0)
    behind = centroid - 5.0 * outward.normals.mean(axis=0)
    at_sensor = Scan(scan.name, scan.path, scan.points, sensor_origin=behind)
    pre = preprocess(at_sensor, voxel)
    assert pre.orientation == "sensor origin"
    assert np.mean(np.einsum("ij,ij->i", pre.normals, outward.normals) < 0) > 0.99


def test_resample_keeps_the_orientation(synthetic, synthetic_pre):
    scan = synthetic[0][0]
    pre = synthetic_pre[0][0]
    pts, nrm = resample(scan, pre, 0.25 * pre.voxel_size)
    assert len(pts) > 2 * len(pre.fine_points)
    _, idx = cKDTree(pre.points).query(pts)
    assert np.mean(np.einsum("ij,ij->i", nrm, pre.normals[idx]) > 0) > 0.99


def test_view_direction_is_found_for_views_only(synthetic, synthetic_pre):
    pre, _ = synthetic_pre
    for p, true_dir in zip(pre, synthetic[3], strict=True):
        assert p.view_facing > 0.95
        angle = np.degrees(np.arccos(np.clip(p.view_direction @ true_dir, -1, 1)))
        assert angle < 6.0, (p.name, angle)
    # All-round normals (a closed surface) face no single direction.
    sphere = np.random.default_rng(0).normal(size=(3000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    assert view_direction(sphere)[1] < 0.6
    d, share = view_direction(sphere[sphere @ [0.0, 0.6, 0.8] > 0.1])
    assert share > 0.99 and d @ [0.0, 0.6, 0.8] > np.cos(np.radians(4))


def test_view_axis_survives_flipped_patches_and_rejects_merged_clouds(synthetic, synthetic_pre):
    """Spanning-tree orientation can flip whole patches (thin parts); the view axis from
    unoriented normals does not care, and re-orienting by it repairs them."""
    pre, T_world_local = synthetic_pre
    p, true_dir = pre[0], synthetic[3][0]
    flipped = p.normals * np.where(p.points[:, 0] > np.median(p.points[:, 0]), -1.0, 1.0)[:, None]
    axis = single_view_axis(p.points, flipped, p.voxel_size)
    assert np.degrees(np.arccos(abs(axis @ true_dir))) < 8.0
    repaired = flipped * np.where(flipped @ axis < 0, -1.0, 1.0)[:, None]
    assert abs(np.mean(np.einsum("ij,ij->i", repaired, p.normals) > 0) - 0.5) > 0.49
    # Single views are height fields along their axis; the three views merged are not.
    for q in pre:
        assert view_axis_occlusion(q.points, q.normals, q.voxel_size)[1] < 0.15
    merged_pts = np.vstack(
        [transform_points(T, q.points) for T, q in zip(T_world_local, pre, strict=True)]
    )
    merged_nrm = np.vstack(
        [q.normals @ T[:3, :3].T for T, q in zip(T_world_local, pre, strict=True)]
    )
    assert view_axis_occlusion(merged_pts, merged_nrm, p.voxel_size)[1] > 0.3
    assert single_view_axis(merged_pts, merged_nrm, p.voxel_size) is None


def test_isolated_outliers_are_removed(synthetic):
    scan = synthetic[0][0]
    rng = np.random.default_rng(1)
    lo, hi = scan.points.min(axis=0), scan.points.max(axis=0)
    outliers = rng.uniform(lo, hi, size=(len(scan.points) // 10, 3))
    noisy = Scan("noisy.npy", Path("noisy.npy"), np.vstack([scan.points, outliers]))
    voxel = derive_voxel_size([scan])
    assert derive_voxel_size([noisy]) == pytest.approx(voxel, rel=0.15)
    keep = outlier_mask(noisy.points, voxel)
    assert keep[: len(scan.points)].mean() > 0.98  # the surface stays
    assert keep[len(scan.points) :].mean() < 0.1  # stray points go
    assert preprocess(noisy, voxel).num_outliers_removed > 0.9 * len(outliers)


# ----------------------------------------------------------------------------- pairs


def test_candidate_pairs_all_or_nearest(synthetic_pre):
    pre = synthetic_pre[0]
    assert candidate_pairs(pre) == [(0, 1), (0, 2), (1, 2)]
    many = [pre[k % 3] for k in range(12)]
    cfg = PairsConfig(all_pairs_max_scans=5, neighbours_per_scan=2)
    pairs = candidate_pairs(many, cfg)
    assert len(pairs) <= 12 * 2 and len(set(pairs)) == len(pairs)
    assert all(i < j for i, j in pairs)
    assert {k for pair in pairs for k in pair} == set(range(12))


def test_synthetic_pair_is_accurate_and_scored_honestly(synthetic_pre):
    pre, T_world_local = synthetic_pre
    truth = invert_transform(T_world_local[0]) @ T_world_local[1]
    result = align_pair(pre[0], pre[1], seed=1, i=0, j=1)
    assert result.accepted, result
    rot, trans = relative_error(result.T_i_j, truth)
    assert rot < 0.3 and trans < 0.003  # object size 1
    assert result.residual_ratio < 2.5 and result.overlap_ratio > 0.3
    assert result.num_correspondences > 500 and result.reason == ""
    # The true pose scores like the estimate; a wrong pose scores as wrong.
    true_scores = score_alignment(pre[0], pre[1], truth)
    assert true_scores["residual_ratio"] < 2.5
    wrong = truth @ make_transform(Rotation.from_euler("z", 20, degrees=True).as_matrix(), 0)
    assert score_alignment(pre[0], pre[1], wrong)["residual_ratio"] > 5
    # Free space: the right pose sees nothing through empty space; turned by 20 degrees
    # about the overlap, surfaces pass through each other.
    assert result.free_space_violation < 0.002
    assert free_space_violation(pre[0], pre[1], truth) < 0.002
    centre = transform_points(truth, pre[1].points).mean(axis=0)
    turn = Rotation.from_rotvec(np.radians(20) * pre[0].view_direction).as_matrix()
    turned = make_transform(turn, centre - turn @ centre) @ truth
    assert free_space_violation(pre[0], pre[1], turned) > 0.05
    # Unseen: the right pose puts nothing where the other view saw only background; turned
    # by 20 or 90 degrees, parts of the surface end up there.
    assert result.unseen_violation < 0.005 and unseen_violation(pre[0], pre[1], truth) < 0.005
    assert unseen_violation(pre[0], pre[1], turned) > 0.03
    turn = Rotation.from_rotvec(np.radians(90) * pre[0].view_direction).as_matrix()
    turned = make_transform(turn, centre - turn @ centre) @ truth
    assert unseen_violation(pre[0], pre[1], turned) > 0.2


def test_non_overlapping_pair_is_rejected(synthetic_pre):
    pre, _ = synthetic_pre
    result = align_pair(pre[0], pre[2], seed=1, i=0, j=2)  # front and back views
    assert not result.accepted and result.reason


def test_alignment_is_deterministic(synthetic_pre):
    pre, _ = synthetic_pre
    pairs = [(0, 1), (0, 2), (1, 2)]
    one = align_pairs(pre, pairs, AlignConfig(), seed=5, executor=1)
    two = align_pairs(pre, pairs, AlignConfig(), seed=5, executor=2)
    again = align_pairs(pre, pairs, AlignConfig(), seed=5, executor=2)
    for a, b, c in zip(one, two, again, strict=True):
        np.testing.assert_array_equal(a.T_i_j, b.T_i_j)
        np.testing.assert_array_equal(a.T_i_j, c.T_i_j)
        assert (a.accepted, a.num_correspondences) == (b.accepted, b.num_correspondences)
    assert pair_seed(5, 0, 1) != pair_seed(5, 0, 2) != pair_seed(6, 0, 1)


def test_open3d_backend_still_works(synthetic_pre):
    pre, T_world_local = synthetic_pre
    cfg = AlignConfig(ransac_backend="open3d")
    result = align_pair(pre[0], pre[1], cfg, seed=1)
    again = align_pair(pre[0], pre[1], cfg, seed=1)
    truth = invert_transform(T_world_local[0]) @ T_world_local[1]
    assert result.accepted
    assert relative_error(result.T_i_j, truth)[0] < 0.3
    np.testing.assert_array_equal(result.T_i_j, again.T_i_j)


def test_relative_residual_rule():
    def result(k, overlap, ratio):
        return PairResult(0, k, np.eye(4), overlap, 0.0, 100, 0.5, True, "", ratio)

    results = [result(1, 0.8, 0.50), result(2, 0.7, 0.55), result(3, 0.6, 0.52)]
    results += [result(4, 0.4, 0.58), result(5, 0.45, 0.95), result(6, 0.3, 1.3)]
    reference = reject_relative_outliers(results, AlignConfig(relative_residual_factor=1.5))
    assert reference == pytest.approx(0.52)
    assert [r.accepted for r in results] == [True, True, True, True, False, False]
    assert "best-overlapping pairs" in results[4].reason
    assert reject_relative_outliers(results[:2]) is None


def test_trimmed_icp_is_not_dragged_by_a_surface_the_target_lacks():
    """A box corner (three planes, every degree of freedom fixed) whose source also holds a
    layer 0.6 voxel above half the floor, a surface the target does not have: within a
    voxel its points match the floor and pull the untrimmed ICP a third of a voxel off.
    Trimming to the noise band, halved down from the voxel, brings it back to the noise
    level, from that biased pose or from the start; a single narrow band from the biased
    pose loses most of the true matches and stays off."""
    from mvreg.pairwise.icp import icp_point_to_plane, icp_trimmed

    rng = np.random.default_rng(0)
    step, v, noise = 0.05, 0.5, 0.002
    g = np.arange(0, 2, step)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    z = np.zeros_like(x)
    planes = [(np.c_[x, y, z], (0, 0, 1)), (np.c_[x, z, y], (0, 1, 0)), (np.c_[z, x, y], (1, 0, 0))]
    tgt = np.concatenate([p for p, _ in planes])
    tn = np.concatenate([np.tile(n, (len(p), 1)) for p, n in planes]).astype(float)
    true = tgt + rng.normal(scale=noise, size=tgt.shape) * tn
    layer = np.c_[x[x > 1.0], y[x > 1.0], np.full(np.count_nonzero(x > 1.0), 0.3)]
    src = np.concatenate([true, layer])
    sn = np.concatenate([tn, np.tile([0.0, 0.0, 1.0], (len(layer), 1))])
    tree = cKDTree(tgt)
    start = make_transform(
        Rotation.from_rotvec([0.01, -0.01, 0.02]).as_matrix(), [0.05, -0.03, 0.04]
    )

    def off(T):  # the largest motion of the true points from their place
        return float(np.abs(transform_points(T, true) - true).max())

    plain = icp_point_to_plane(src, sn, tgt, tn, tree, start, v, 60, 0.5)
    assert off(plain) > 0.25 * v
    for T0 in (plain, start):
        assert off(icp_trimmed(src, sn, tgt, tn, tree, T0, v, 3 * noise, 0.5)) < 0.1 * noise
    narrow = icp_point_to_plane(src, sn, tgt, tn, tree, plain, v, 30, 0.5, max_residual=3 * noise)
    assert off(narrow) > 0.1 * v


# ----------------------------------------------------------------------------- correspondences


def test_fast_helpers_match_numpy_bit_for_bit():
    """ICP's cross product and norms skip NumPy's dispatch (called hundreds of thousands
    of times a run): they must give the same floats, or results would change."""
    from mvreg.geometry import cross3, norm2

    rng = np.random.default_rng(0)
    for n in (1, 7, 400, 5000):
        a = rng.normal(size=(n, 3)) * rng.uniform(1e-6, 1e6, (n, 1))
        b = rng.normal(size=(n, 3))
        assert np.array_equal(cross3(a, b), np.cross(a, b))
        assert norm2(a) == float(np.linalg.norm(a)) and norm2(a[0]) == float(np.linalg.norm(a[0]))


def test_mutual_correspondences():
    rng = np.random.default_rng(0)
    pts = rng.uniform(size=(500, 3))
    T = make_transform(Rotation.random(random_state=1).as_matrix(), [1.0, 2.0, 3.0])
    moved = transform_points(invert_transform(T), pts)  # scan j's copy of the same points
    idx_i, idx_j = mutual_correspondences(pts, moved, T, 0.01)
    np.testing.assert_array_equal(idx_i, np.arange(500))
    np.testing.assert_array_equal(idx_j, np.arange(500))
    # Nothing within reach.
    far = make_transform(np.eye(3), [0.5, 0.0, 0.0]) @ T
    shifted_i, _ = mutual_correspondences(pts, moved, far, 1e-3)
    assert len(shifted_i) == 0
    # Normal test: opposite normals never match.
    normals = np.tile([0.0, 0.0, 1.0], (500, 1))
    normals_j = normals @ T[:3, :3]  # the same normals in j's frame
    kept, _ = mutual_correspondences(
        pts, moved, T, 0.01, normals_i=normals, normals_j=normals_j, min_normal_cos=0.5
    )
    assert len(kept) == 500
    none, _ = mutual_correspondences(
        pts, moved, T, 0.01, normals_i=-normals, normals_j=normals_j, min_normal_cos=0.5
    )
    assert len(none) == 0
    # Only mutual pairs: two i points near one j point give one correspondence.
    a = np.array([[0.0, 0, 0], [0.004, 0, 0]])
    b = np.array([[0.001, 0, 0]])
    idx_i, idx_j = mutual_correspondences(a, b, np.eye(4), 0.01)
    assert idx_i.tolist() == [0] and idx_j.tolist() == [0]
    # Partly overlapping noisy sets: the same pairs as a brute-force mutual search.
    a = rng.uniform(size=(400, 3))
    b = np.vstack([a[:200] + rng.normal(scale=0.01, size=(200, 3)), rng.uniform(size=(150, 3))])
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    ab, ba = d.argmin(axis=1), d.argmin(axis=0)
    want = [(ba[k], k) for k in range(len(b)) if ab[ba[k]] == k and d[ba[k], k] <= 0.02]
    idx_i, idx_j = mutual_correspondences(a, b, np.eye(4), 0.02)
    assert sorted(zip(idx_i.tolist(), idx_j.tolist(), strict=True)) == sorted(want)
    assert len(want) > 100


# ----------------------------------------------------------------------------- tracks


def test_tracks_union_find_conflicts_and_weights():
    points = [np.arange(3 * k, dtype=float).reshape(k, 3) for k in (4, 4, 4)]
    names = ["a", "b", "c"]
    pairs = np.array([[0, 1], [1, 2], [0, 2]])
    # a0-b0-c0 consistent; a1-b1, b1-c1, c1-a2: a chain seeing scan a twice; a3-b3 alone.
    corr = [
        (np.array([0, 1, 3]), np.array([0, 1, 3])),
        (np.array([0, 1]), np.array([0, 1])),
        (np.array([0, 2]), np.array([0, 1])),
    ]
    distances = [np.array([0.1, 0.1, 0.1]), np.array([0.1, 0.5]), np.array([0.1, 0.2])]
    split = tracks_from_correspondences(points, names, pairs, corr, distances=distances)
    drop = tracks_from_correspondences(
        points, names, pairs, corr, distances=distances, split_conflicts=False
    )
    for tr in (split, drop):
        key = tr.obs_node * 3 + tr.obs_scan
        assert len(np.unique(key)) == len(key)  # no track sees a scan twice
        assert tr.num_conflicting_tracks == 1
        np.testing.assert_array_equal(tr.coords, np.stack(
            [points[s][p] for s, p in zip(tr.obs_scan, tr.obs_point, strict=True)]
        ))  # fmt: skip
        assert tr.problem.patch_names == names and tr.unconnected_scans == []
    # Drop: the conflicting chain goes; {a0,b0,c0} and {a3,b3} stay.
    assert drop.num_tracks == 2 and drop.num_dropped_tracks == 1 and drop.num_observations == 5
    # Split (shortest links first): the longest link b1-c1 (0.5) is refused.
    assert split.num_tracks == 4 and split.num_refused_links == 1
    groups = [
        sorted(zip(split.obs_scan[mask].tolist(), split.obs_point[mask].tolist(), strict=True))
        for mask in (split.obs_node == n for n in range(split.num_tracks))
    ]
    assert [(0, 0), (1, 0), (2, 0)] in groups
    assert [(0, 2), (2, 1)] in groups
    # Links and their pairs, and re-weighting a pair to 0 removes its links.
    for (oa, ob), p in zip(split.link_obs, split.link_pair, strict=True):
        i, j = pairs[p]
        assert {split.obs_scan[oa], split.obs_scan[ob]} == {i, j}
        assert split.obs_node[oa] == split.obs_node[ob]
    assert np.all(split.obs_pair >= 0)
    no_ca = split.reweighted([1.0, 1.0, 0.0])
    assert 2 not in no_ca.link_pair.tolist()
    assert no_ca.num_conflicting_tracks == 0
    half = split.reweighted([0.5, 1.0, 1.0])
    a3 = (half.obs_scan == 0) & (half.obs_point == 3)
    assert half.weight[a3].tolist() == [0.5]


def test_tracks_report_unconnected_scans():
    points = [np.random.default_rng(k).uniform(size=(10, 3)) for k in range(3)]
    corr = [(np.arange(6), np.arange(6))]
    tr = tracks_from_correspondences(points, ["x", "y", "z"], np.array([[0, 1]]), corr)
    assert tr.unconnected_scans == ["z"]
    assert tr.problem.patch_names == ["x", "y"] and tr.patch_scans.tolist() == [0, 1]
    empty = tracks_from_correspondences(points, ["x", "y", "z"], np.zeros((0, 2)), [])
    assert empty.problem is None and empty.num_tracks == 0


def test_synthetic_tracks_build_a_patch_problem(synthetic_pre):
    pre, T_world_local = synthetic_pre
    results = align_pairs(pre, candidate_pairs(pre), seed=0)
    tracks = build_tracks(pre, results, TracksConfig())
    problem = tracks.problem
    assert problem is not None and problem.num_patches == 2  # back view overlaps nothing
    assert tracks.unconnected_scans == ["back.npy"]
    T = np.stack(T_world_local)[tracks.obs_scan]
    world = np.einsum("kij,kj->ki", T[:, :3, :3], tracks.coords) + T[:, :3, 3]
    a, b = tracks.link_obs.T
    assert np.median(np.linalg.norm(world[a] - world[b], axis=1)) < 0.5 * pre[0].fine_voxel_size


# ----------------------------------------------------------------------------- Stanford bunny


def bun_conf(path: Path) -> dict[str, np.ndarray]:
    """T_world_scan of each scan: p_world = R(q)^T p + t (README of shared/data)."""
    poses = {}
    for line in path.read_text().splitlines():
        parts = line.split()
        if parts and parts[0] == "bmesh":
            t = np.array(parts[2:5], float)
            q = np.array(parts[5:9], float)
            poses[parts[1]] = make_transform(Rotation.from_quat(q).as_matrix().T, t)
    return poses


@pytest.fixture(scope="module")
def bunny(request):
    shared = request.getfixturevalue("shared_data")
    folder = shared / "stanford_bunny_scans"
    scans = load_scans(folder)
    voxel = derive_voxel_size(scans)
    pre = [preprocess(s, voxel) for s in scans]
    index = {s.name: k for k, s in enumerate(scans)}
    return scans, pre, index, bun_conf(folder / "bun.conf")


def bunny_truth(poses, name_i, name_j):
    return invert_transform(poses[name_i]) @ poses[name_j]


def test_bun_conf_convention(bunny):
    scans, _, index, poses = bunny
    a, b = scans[index["bun000.ply"]], scans[index["bun045.ply"]]
    world_a = transform_points(poses[a.name], a.points)
    world_b = transform_points(poses[b.name], b.points)
    d, _ = cKDTree(world_a).query(world_b[::5])
    assert np.median(d[d < 5e-4]) < 3e-4 and np.mean(d < 5e-4) > 0.8


@pytest.mark.parametrize(
    ("name_i", "name_j"),
    [
        ("bun000.ply", "bun045.ply"),
        ("bun045.ply", "bun090.ply"),
        ("bun000.ply", "chin.ply"),
        ("bun180.ply", "ear_back.ply"),
        ("ear_back.ply", "top2.ply"),
    ],
)
def test_bunny_pairs_match_bun_conf(bunny, name_i, name_j):
    _, pre, index, poses = bunny
    i, j = index[name_i], index[name_j]
    result = align_pair(pre[i], pre[j], seed=pair_seed(0, i, j), i=i, j=j)
    assert result.accepted, result
    rot, trans = relative_error(result.T_i_j, bunny_truth(poses, name_i, name_j))
    assert rot < 1.0 and trans < 2e-3, (rot, trans)  # measured <= 0.2 deg, 0.3 mm


@pytest.mark.parametrize(
    ("name_i", "name_j"), [("chin.ply", "ear_back.ply"), ("bun000.ply", "bun180.ply")]
)
def test_bunny_low_overlap_pairs_are_rejected(bunny, name_i, name_j):
    _, pre, index, poses = bunny
    i, j = index[name_i], index[name_j]
    result = align_pair(pre[i], pre[j], seed=pair_seed(0, i, j), i=i, j=j)
    assert not result.accepted
    rot, _ = relative_error(result.T_i_j, bunny_truth(poses, name_i, name_j))
    assert rot > 5.0  # a wrong alignment, which the scores expose
    assert result.residual_ratio > 3 * AlignConfig().max_residual_ratio
    if np.isfinite(result.free_space_violation):
        assert result.free_space_violation > 5 * AlignConfig().max_free_space_violation
    # Even the true relative pose of chin / ear_back shows little real overlap.
    if name_i == "chin.ply":
        true_scores = score_alignment(pre[i], pre[j], bunny_truth(poses, name_i, name_j))
        assert true_scores["overlap_ratio"] < 0.15


def test_bunny_all_pairs_and_tracks(bunny):
    scans, pre, _, poses = bunny
    pairs = candidate_pairs(pre)
    assert len(pairs) == 45
    results = align_pairs(pre, pairs, seed=0)
    accepted = [r for r in results if r.accepted]
    assert len(accepted) >= 20
    for r in results:
        rot, trans = relative_error(r.T_i_j, bunny_truth(poses, scans[r.i].name, scans[r.j].name))
        if r.accepted:  # every accepted pair is right, and sees nothing through free space
            assert rot < 1.0 and trans < 2e-3, r
            assert r.free_space_violation < 0.002, r
    assert all(p.view_direction is not None for p in pre)  # range scans: single views
    tracks = build_tracks(pre, results)
    assert tracks.unconnected_scans == [] and tracks.problem.num_patches == 10
    key = tracks.obs_node * len(scans) + tracks.obs_scan
    assert len(np.unique(key)) == len(key)
    assert tracks.num_tracks > 5000
    # Correspondences agree with bun.conf: linked points lie close in the true world frame.
    T = np.stack([poses[s.name] for s in scans])[tracks.obs_scan]
    world = np.einsum("kij,kj->ki", T[:, :3, :3], tracks.coords) + T[:, :3, 3]
    a, b = tracks.link_obs.T
    assert np.median(np.linalg.norm(world[a] - world[b], axis=1)) < 1e-3


def test_cycle_check_sets_aside_the_pair_the_geometry_contradicts(synthetic_pre):
    """A triangle with one wrong pair: counting cycles ties all three pairs, and the
    count's tie-break (smaller overlap first) sets aside a right one. Tested against the
    pose the cycle implies, the wrong pair loses on the scans' own points."""
    from mvreg.pairwise.consistency import inconsistent_pairs

    pre, T_world = synthetic_pre
    results = []
    for i, j, overlap in ((0, 1, 0.9), (1, 2, 0.5), (0, 2, 0.4)):
        T = invert_transform(T_world[i]) @ T_world[j]
        if (i, j) == (0, 1):  # 12 degrees about the overlap's centre, as a slide would be
            c = transform_points(T, pre[j].points).mean(axis=0)
            R = Rotation.from_rotvec(np.radians(12.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
            T = make_transform(R, c - R @ c) @ T
        results.append(
            PairResult(i, j, T, overlap_ratio=overlap, inlier_rmse=0.0,
                       num_correspondences=500, fitness=0.5, accepted=True, reason="")
        )  # fmt: skip
    by_count = inconsistent_pairs(pre, results, max_voxels=2.0)
    assert [(results[k].i, results[k].j) for k, _ in by_count] == [(0, 2)]  # a right pair
    out = inconsistent_pairs(pre, results, max_voxels=2.0, align_cfg=AlignConfig())
    assert [(results[k].i, results[k].j) for k, _ in out] == [(0, 1)]
    info = out[0][1]
    assert info["best_cycle_support"] > max(100.0, info["own_support"])


def test_absurdly_small_given_voxel_is_refused_naming_the_value():
    """Issue 16: `--voxel-size 1e-7` ran 26 s and registered nothing; now refused at once."""
    from mvreg.errors import ConfigError
    from mvreg.pairwise import derive_scales

    rng = np.random.default_rng(0)
    scans = [Scan(name=f"s{k}", path=None, points=rng.uniform(0, 1, (2000, 3))) for k in range(2)]
    with pytest.raises(ConfigError, match="voxel_size 1e-07 is far below"):
        derive_scales(scans, PreprocessConfig(voxel_size=1e-7))
    assert derive_scales(scans, PreprocessConfig(voxel_size=0.05)).voxel == 0.05


@pytest.mark.parametrize("scans", [5, 70, 150])
def test_split_conflicts_in_runs_equals_one_link_at_a_time(scans):
    """The run-wise split (arrays for what cannot be refused) gives the partial tracks and
    refusals of the plain greedy union-find, shortest links first; scan sets wider than
    one 64-bit word included."""
    from mvreg.pairwise.tracks import split_tracks

    rng = np.random.default_rng(scans)
    n, e = 3000, 9000
    vert_scan = rng.integers(0, scans, n)
    vert_scan[0] = scans - 1
    ea, eb = rng.integers(0, n, e), rng.integers(0, n, e)
    edge_len = np.round(rng.uniform(0, 1, e), 2)  # ties too
    label = np.zeros(n, np.int64)
    bad = np.array([True])
    parent, sets, refused = list(range(n)), [{int(s)} for s in vert_scan], 0

    def find(a):
        while parent[a] != a:
            a = parent[a]
        return a

    for k in np.argsort(edge_len, kind="stable"):
        a, b = find(ea[k]), find(eb[k])
        if a == b:
            continue
        if sets[a] & sets[b]:
            refused += 1
            continue
        a, b = min(a, b), max(a, b)
        parent[b] = a
        sets[a] |= sets[b]
    expect = np.array([find(v) for v in range(n)]) + 1
    got, got_refused = split_tracks(label, 1, bad, ea, eb, edge_len, vert_scan)
    assert got_refused == refused > 0
    assert np.array_equal(got, expect)


def test_a_view_seen_through_another_contradicts_it_without_shared_surface(synthetic_pre):
    """More than half of a scan's facing points in another scan's free space is a conflict
    whatever the surface they share (mvreg.globalstage.conflicts): the back view turned
    to face the front sensor and moved 0.3 towards it shares no close match with the
    front view, yet lies in the space the front view saw through. At the true poses,
    neither test reads anything of note and there is no conflict."""
    import copy

    from mvreg.globalstage.conflicts import free_space_conflicts
    from mvreg.globalstage.verify import ScanVerification
    from mvreg.pairwise.view_projection import set_viewpoint

    pre, T_world_local = synthetic_pre
    names, acfg = [p.name for p in pre], AlignConfig()
    # Uniform samples show no sensor grid: seen along their axes, a bound on the share
    # does not apply. Give the two views sensors 20 radii out along their axes (nearly
    # the same projection).
    orthographic = pre
    pre = copy.deepcopy(pre)
    for p in (pre[0], pre[2]):
        centre = p.fine_points.mean(0)
        radius = float(np.sqrt(np.mean(np.sum((p.fine_points - centre) ** 2, axis=1))))
        set_viewpoint(p, centre + 20.0 * radius * p.view_direction, p.normals)
        p._cache.clear()
    truth = {0: T_world_local[0], 2: T_world_local[2]}
    v = ScanVerification(status="verified")
    assert free_space_conflicts(v, 2, [0], [], pre, truth, names, acfg) == []
    assert v.free_space_violation < 0.01
    centre = transform_points(T_world_local[2], pre[2].points).mean(axis=0)
    turn = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    front = transform_points(T_world_local[0], pre[0].points).mean(axis=0) - centre
    shift = 0.3 * np.array([1.0, 0.0, 0.0]) + np.array([front[0], 0.0, 0.0])
    moved = make_transform(turn, centre - turn @ centre + shift) @ T_world_local[2]
    placed = {0: T_world_local[0], 2: moved}
    conflicts = free_space_conflicts(v, 2, [0], [], pre, placed, names, acfg)
    assert v.free_space_violation > acfg.max_free_space_apart
    assert [(k, gross) for k, _, gross in conflicts] == [(0, True)]
    assert "front.npy's free space" in conflicts[0][1]
    # Not gross below the bound, and then not a conflict with a scan outside the support
    loose = acfg.model_copy(update={"max_free_space_apart": 1.0})
    assert free_space_conflicts(v, 2, [0], [], pre, placed, names, loose) == []
    # Nor between views without a sensor position
    assert free_space_conflicts(v, 2, [0], [], orthographic, placed, names, acfg) == []
    assert v.free_space_violation > acfg.max_free_space_apart
