"""Cycle check of accepted pairs (mvreg.pairwise.consistency) and the refinement's pair ICP."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mvreg.geometry import invert_transform, transform_points
from mvreg.pairwise.consistency import inconsistent_pairs
from mvreg.pairwise.result import PairResult


def _pose(rng, angle_deg=None, shift=1.0):
    T = np.eye(4)
    if angle_deg is None:
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    else:
        axis = rng.normal(size=3)
        T[:3, :3] = Rotation.from_rotvec(
            np.radians(angle_deg) * axis / np.linalg.norm(axis)
        ).as_matrix()
    T[:3, 3] = shift * rng.normal(size=3)
    return T


def _setup(num_scans=6, wrong=(), noise_deg=0.2, seed=0):
    """Scans of random points (unit cube, voxel 0.05), true poses, every pair accepted with
    its true relative pose perturbed by ``noise_deg``; pairs in ``wrong`` get 12 deg."""
    rng = np.random.default_rng(seed)
    pre = [
        SimpleNamespace(points=rng.uniform(-0.5, 0.5, (400, 3)), voxel_size=0.05)
        for _ in range(num_scans)
    ]
    truth = [_pose(rng) for _ in range(num_scans)]
    results = []
    for i in range(num_scans):
        for j in range(i + 1, num_scans):
            T = invert_transform(truth[i]) @ truth[j]
            err = _pose(rng, 12.0 if (i, j) in wrong else noise_deg, 0.0)
            results.append(
                PairResult(i, j, err @ T, overlap_ratio=0.5, inlier_rmse=0.0,
                           num_correspondences=100, fitness=0.5, accepted=True, reason="")
            )  # fmt: skip
    return pre, results


def test_consistent_pairs_are_all_kept():
    pre, results = _setup()
    assert inconsistent_pairs(pre, results, max_voxels=2.0) == []


@pytest.mark.parametrize("wrong", [((0, 3),), ((1, 2), (3, 5))])
def test_wrong_pairs_are_set_aside_and_only_they(wrong):
    pre, results = _setup(wrong=wrong)
    out = inconsistent_pairs(pre, results, max_voxels=2.0)
    found = {(results[k].i, results[k].j) for k, _ in out}
    assert found == set(wrong)
    for _, info in out:
        assert info["inconsistent_cycles"] > info["consistent_cycles"]
        assert info["median_discrepancy_voxels"] > 2.0


def test_pair_without_cycles_is_kept():
    pre, results = _setup(num_scans=3, wrong=((0, 1),))
    # Only the chain 0-1, 1-2 is accepted: no cycle, nothing to contradict the wrong pair.
    results = [r for r in results if (r.i, r.j) != (0, 2)]
    assert inconsistent_pairs(pre, results) == []


def test_pair_icp_recovers_a_slide_along_planes():
    """Refinement's pair ICP (point-to-plane) on two views of a box corner: from a pose
    slid along the faces by 0.6 voxel and turned by 1 degree it returns to the truth,
    which nearest-neighbour correspondences under the start pose would not state."""
    from mvreg.globalstage.refine import pair_icp

    rng = np.random.default_rng(1)
    g = np.linspace(0.0, 1.0, 41)
    u, w = (a.ravel() for a in np.meshgrid(g, g))
    zero = np.zeros_like(u)
    faces = [np.stack(c, 1) for c in ((u, w, zero), (u, zero, w), (zero, u, w))]
    normals = [np.tile(n, (len(u), 1)) for n in np.eye(3)[[2, 1, 0]]]
    pts = np.vstack(faces) + 1e-4 * rng.normal(size=(3 * len(u), 3))
    nrm = np.vstack(normals)
    pts_j, nrm_j = pts[1::2], nrm[1::2]  # another sampling of the same corner
    voxel = 0.05
    T_start = np.eye(4)
    T_start[:3, :3] = Rotation.from_rotvec(np.radians([0.0, 0.0, 1.0])).as_matrix()
    T_start[:3, 3] = [0.6 * voxel, -0.4 * voxel, 0.0]
    T = pair_icp(pts, nrm, cKDTree(pts), pts_j, nrm_j, T_start, voxel, 0.5)
    assert T is not None
    err = np.linalg.norm(transform_points(T, pts_j) - pts_j, axis=1)
    start = np.linalg.norm(transform_points(T_start, pts_j) - pts_j, axis=1)
    assert np.max(start) > 0.5 * voxel
    assert np.max(err) < 0.02 * voxel


def test_support_prefers_the_hypothesis_outside_free_space():
    """Teapot seed 1, scan_005-scan_010: the flip passed the rule with 3986 correspondences
    and 0.003 of its points in free space, the right pose with 4002 and 0.000."""
    from mvreg.config import AlignConfig
    from mvreg.pairwise.decision import support

    cfg = AlignConfig()
    flip = {"num_correspondences": 3986, "free_space_violation": 0.003}
    right = {"num_correspondences": 4002, "free_space_violation": 0.0}
    assert support(right, cfg) > 2 * support(flip, cfg)
    no_view = {"num_correspondences": 100, "free_space_violation": float("nan")}
    assert support(no_view, cfg) == 100


def test_robust_rounds_never_cut_a_scan_off():
    """Zeroing pairs by residual keeps every scan connected: of the zeroed pairs, the ones
    that alone join two parts come back at the floor weight, lowest residual first."""
    from mvreg.globalstage.robust import keep_connected

    # 0-1-2 triangle, 2-3 the only link of scan 3, 3-4 and 2-4 two links of scan 4.
    pairs = np.array([(0, 1), (1, 2), (0, 2), (2, 3), (3, 4), (2, 4)])
    before = np.ones(6)
    residual = np.array([1.0, 1.0, 9.0, 8.0, 7.0, 6.0])
    after = np.array([1.0, 1.0, 0.0, 0.0, 0.0, 0.0])  # 0-2 and every link of 3 and 4 zeroed
    out = keep_connected(pairs, before, after, residual, 0.05)
    # 0-2 stays zero (0 and 2 are joined by 0-1-2); 2-4 (lower residual) brings 4 back,
    # then 3-4 (lower than 2-3) brings 3 back.
    assert out.tolist() == [1.0, 1.0, 0.0, 0.0, 0.05, 0.05]
    # Pairs zero before stay zero: a scan cut off earlier is not for this rule to restore.
    assert keep_connected(pairs, after, after, residual, 0.05).tolist() == after.tolist()
