"""Guided RANSAC sampling (mvreg.pairwise.guided): triples drawn among pairwise-consistent
matches find the pose where plain triples cannot (2% inliers), and the graph is right."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from mvreg.config import AlignConfig
from mvreg.geometry import make_transform, rotation_angle_deg, transform_points
from mvreg.pairwise.guided import compatibility, draw_triples
from mvreg.pairwise.hypotheses import ransac_numpy


def _matches(m: int, inliers: int, seed: int, noise: float = 0.005):
    """Points on a unit sphere with outward normals; ``inliers`` matches follow T, the
    rest pair random points. Returns (src, dst, src_n, dst_n, T, inlier mask)."""
    rng = np.random.default_rng(seed)
    T = make_transform(Rotation.random(random_state=seed).as_matrix(), rng.normal(size=3))
    src = rng.normal(size=(m, 3))
    src /= np.linalg.norm(src, axis=1, keepdims=True)
    src_n = src.copy()
    dst = transform_points(T, src) + rng.normal(scale=noise, size=(m, 3))
    dst_n = src_n @ T[:3, :3].T
    out = np.arange(inliers, m)
    perm = rng.permutation(out)
    dst[out], dst_n[out] = dst[perm], dst_n[perm]  # outliers: another point's partner
    mask = np.zeros(m, bool)
    mask[:inliers] = True
    return src, dst, src_n, dst_n, T, mask


def test_compatibility_keeps_every_inlier_pair_and_few_others():
    src, dst, sn, dn, _, inl = _matches(600, 30, seed=1)
    indptr, indices = compatibility(src, dst, sn, dn, dist=0.02, normal_deg=30.0, min_length=0.05)
    rows = np.repeat(np.arange(len(src)), np.diff(indptr))
    both = inl[rows] & inl[indices]
    # every pair of inliers (apart from too-short edges) is compatible
    pairs_in = both.sum()
    d = np.linalg.norm(src[inl][:, None] - src[inl][None], axis=2)
    assert pairs_in >= 0.97 * (np.sum(d > 0.05))
    # an outlier pair is compatible only by chance: far rarer than an inlier pair
    out_rate = np.mean(~inl[rows] & ~inl[indices]) * len(rows) / (570 * 569)
    assert out_rate < 0.1  # on a sphere the normals add nothing to the distance test
    # symmetric and sorted per row
    for a in range(0, 600, 37):
        row = indices[indptr[a] : indptr[a + 1]]
        assert np.all(np.diff(row) > 0)
        for b in row[:5]:
            assert a in indices[indptr[b] : indptr[b + 1]]


def test_guided_triples_are_far_more_often_all_inliers():
    src, dst, sn, dn, _, inl = _matches(800, 16, seed=2)
    indptr, indices = compatibility(src, dst, sn, dn, dist=0.02, normal_deg=30.0, min_length=0.05)
    tri = draw_triples(np.random.default_rng(0), indptr, indices, 20000)
    assert len(tri) > 0
    # every drawn pair is compatible
    for a, b in tri[:200, :2]:
        assert b in indices[indptr[a] : indptr[a + 1]]
    share = np.mean(inl[tri].all(axis=1))
    assert share > 50 * (16 / 800) ** 3  # plain draws: w^3 = 8e-6


def test_guided_ransac_finds_the_pose_plain_ransac_misses():
    src, dst, sn, dn, T, _ = _matches(1000, 20, seed=3)
    cfg = AlignConfig()
    voxel = 0.02 / cfg.ransac_distance_voxels
    a = SimpleNamespace(points=dst, normals=dn, _cache={})  # i: the destination
    b = SimpleNamespace(points=src, normals=sn, _cache={})
    idx = (np.arange(1000), np.arange(1000))
    T_plain, st_plain = ransac_numpy(a, b, cfg, 0, None, voxel, matches=idx, guided=False)
    T_g, st_g = ransac_numpy(a, b, cfg, 0, None, voxel, matches=idx, guided=True)
    assert st_g["ok"]
    assert rotation_angle_deg(T_g[:3, :3] @ T[:3, :3].T) < 2.0
    assert np.linalg.norm(T_g[:3, 3] - T[:3, 3]) < 0.05
    # the plain draws (4,000 triples at w = 2%) do not find it
    plain_err = rotation_angle_deg(T_plain[:3, :3] @ T[:3, :3].T)
    assert not st_plain["ok"] or plain_err > 2.0
    # deterministic for a seed
    T_g2, _ = ransac_numpy(a, b, cfg, 0, None, voxel, matches=idx, guided=True)
    assert np.array_equal(T_g, T_g2)
