"""The pairwise aligner interface and registry, the executor seam and the run's scales."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mvreg.config import AlignConfig, PreprocessConfig, SearchConfig
from mvreg.errors import ConfigError
from mvreg.executor import ThreadExecutor
from mvreg.geometry import invert_transform, make_transform, rotation_angle_deg, transform_points
from mvreg.io.loaders import Scan
from mvreg.pairwise import (
    ALIGNERS,
    PairwiseAligner,
    align_pair,
    align_pairs,
    derive_scales,
    derive_voxel_size,
    make_aligner,
    preprocess_all,
    register_aligner,
    scan_scales,
    score_alignment,
    with_noise,
)
from mvreg.pairwise.aligners.base import BaseAligner
from mvreg.pairwise.decision import verify
from mvreg.pairwise.preprocess import check_voxel_size
from mvreg.pairwise.result import pair_result
from mvreg.scales import Scales


@pytest.fixture(scope="module")
def views():
    """Three views of the built-in object (size 1): front and side in random local frames
    (truth known), and the side view again in the front view's frame."""
    trimesh = pytest.importorskip("trimesh")
    from data_synth.builtin import builtin_object

    mesh = builtin_object(0, subdivisions=4)
    points, faces = trimesh.sample.sample_surface(mesh, 40000, seed=3)
    normals = np.asarray(mesh.face_normals)[faces]
    rng = np.random.default_rng(7)
    frames = [make_transform(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))]
    frames.append(make_transform(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)))
    frames.append(frames[0])
    directions = [[1, 0, 0.2], [0.6, 0.8, 0.1], [0.6, 0.8, 0.1]]
    scans = []
    for k, (d, T_local_world) in enumerate(zip(directions, frames, strict=True)):
        keep = normals @ (np.asarray(d, float) / np.linalg.norm(d)) > 0.15
        local = transform_points(T_local_world, points[keep])
        local += np.random.default_rng(k).normal(scale=1e-4, size=local.shape)
        scans.append(Scan(name=f"view{k}.npy", path=Path(f"view{k}.npy"), points=local))
    scales = derive_scales(scans)
    pre = preprocess_all(scans, scales.voxel, executor=2)
    truth = frames[0] @ invert_transform(frames[1])  # T_0_1 (= T_0_2 after the frames)
    return scans, with_noise(scales, pre), pre, truth


def _errors(T, truth):
    return rotation_angle_deg((invert_transform(truth) @ T)[:3, :3]), float(
        np.linalg.norm(T[:3, 3] - truth[:3, 3])
    )


def test_registry_holds_the_three_methods_behind_one_interface():
    assert {"feature-ransac", "icp-guess", "rotation-search"} <= set(ALIGNERS)
    for name in ("feature-ransac", "icp-guess", "rotation-search"):
        aligner = make_aligner(name, AlignConfig(), SearchConfig(), scales=None, executor=1)
        assert isinstance(aligner, PairwiseAligner)
    with pytest.raises(ConfigError, match="unknown pairwise aligner"):
        make_aligner("no-such-method")


def test_a_new_aligner_is_one_class_and_one_registry_line(views):
    """The example of mvreg.pairwise.aligners.base: ICP from the scans' own frames."""
    _, scales, pre, _ = views

    @register_aligner("test-identity-icp")
    class IdentityIcpAligner(BaseAligner):
        def align(self, pre_i, pre_j, guess=None, seed=0, *, i=0, j=1):
            start, scales = time.perf_counter(), self.scales_for(pre_i)
            T0 = np.eye(4) if guess is None else guess
            T, reason, scores, _ = verify(pre_i, pre_j, T0, self.cfg, scales)
            return pair_result(
                pre_i, pre_j, i, j, T, reason, scores, {}, start, fine_voxel=scales.fine_voxel
            )

    try:
        (res,) = align_pairs(
            pre, [(0, 2)], AlignConfig(), scales=scales, method="test-identity-icp"
        )
    finally:
        del ALIGNERS["test-identity-icp"]
    assert res.accepted, res
    rot, trans = _errors(res.T_i_j, np.eye(4))
    assert rot < 0.3 and trans < 0.003


def test_icp_from_a_guess_converges_and_is_decided_by_the_shared_rule(views):
    _, scales, pre, truth = views
    nudge = make_transform(Rotation.from_euler("xz", [2.0, -2.0], degrees=True).as_matrix(), 0.01)
    guess = nudge @ truth
    res = make_aligner("icp-guess", AlignConfig(), scales=scales).align(
        pre[0], pre[1], guess, i=0, j=1
    )
    assert res.accepted, res
    assert res.stats["T_guess"] == guess.tolist()
    rot, trans = _errors(res.T_i_j, truth)
    assert rot < 0.3 and trans < 0.003
    # A guess turned far off does not converge and is rejected by the same rule.
    far = make_transform(Rotation.from_euler("z", 120, degrees=True).as_matrix(), 0) @ truth
    bad = make_aligner("icp-guess", AlignConfig(), scales=scales).align(
        pre[0], pre[1], far, i=0, j=1
    )
    assert not bad.accepted and bad.reason


def test_feature_ransac_through_the_registry_is_align_pair(views):
    _, scales, pre, truth = views
    aligner = make_aligner("feature-ransac", AlignConfig(), scales=scales)
    res = aligner.align(pre[0], pre[1], None, 3, i=0, j=1)
    same = align_pair(pre[0], pre[1], AlignConfig(), 3, i=0, j=1, scales=scales)
    np.testing.assert_array_equal(res.T_i_j, same.T_i_j)
    assert res.accepted and same.accepted
    rot, trans = _errors(res.T_i_j, truth)
    assert rot < 0.3 and trans < 0.003


class SerialExecutor:
    """The executor example of mvreg.executor."""

    workers = 1

    def map(self, fn, items, progress=None):
        out = []
        for item in items:
            out.append(fn(item))
            if progress is not None:
                progress(out[-1])
        return out


def test_rotation_search_needs_no_feature_matches(views):
    _, scales, pre, truth = views
    quick = SearchConfig(weak_scans=True, screen_source_points=100, screen_iterations=2)
    res = make_aligner("rotation-search", AlignConfig(), quick, scales=scales, executor=2).align(
        pre[0], pre[1], i=0, j=1
    )
    assert res.accepted and res.stats["search"]
    rot, trans = _errors(res.T_i_j, truth)
    assert rot < 0.3 and trans < 0.003


def test_any_executor_gives_the_same_pairs_in_the_same_order(views):
    _, scales, pre, _ = views
    pairs = [(0, 1), (1, 2), (0, 2)]
    seen = []
    serial = align_pairs(pre, pairs, seed=4, executor=SerialExecutor(), progress=seen.append)
    threads = align_pairs(pre, pairs, seed=4, executor=ThreadExecutor(2), scales=scales)
    assert [(r.i, r.j) for r in serial] == [(r.i, r.j) for r in seen] == pairs
    for a, b in zip(serial, threads, strict=True):
        np.testing.assert_array_equal(a.T_i_j, b.T_i_j)
        assert (a.accepted, a.reason, a.num_correspondences) == (
            b.accepted,
            b.reason,
            b.num_correspondences,
        )


def test_scales_are_derived_once_and_checked_once(views):
    scans, scales, pre, _ = views
    assert scales.voxel == derive_voxel_size(scans)
    assert scales.fine_voxel == PreprocessConfig().fine_voxel_ratio * scales.voxel
    assert scales.voxel_source == "derived"
    assert scales.noise == float(np.median([p.noise for p in pre])) > 0
    assert scan_scales(pre[0]) == Scales(pre[0].voxel_size, pre[0].fine_voxel_size)
    given = derive_scales(scans, PreprocessConfig(voxel_size=0.05, fine_voxel_ratio=0.25))
    assert (given.voxel, given.fine_voxel, given.voxel_source) == (0.05, 0.0125, "given")
    assert given.noise == 0.0
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="voxel_size must be > 0"):
            check_voxel_size(bad)
    with pytest.raises(ConfigError, match="voxel_size must be > 0"):
        preprocess_all(scans[:1], 0.0)


def test_explicit_scales_give_the_scores_of_the_scans_own(views):
    _, scales, pre, truth = views
    own = score_alignment(pre[0], pre[1], truth)
    explicit = score_alignment(pre[0], pre[1], truth, scales=scales)
    assert own.keys() == explicit.keys()
    assert all(np.array_equal(own[k], explicit[k], equal_nan=True) for k in own)


def test_a_scan_no_cycle_confirms_has_its_rejected_pairs_searched(views):
    """Scan 1 with both its pairs rejected (a wrong pose each) is searched again and
    comes back confirmed by the triangle, within 0.3 deg of the truth; where every scan is
    confirmed nothing is searched (the very same results come back)."""
    from dataclasses import replace

    from mvreg.pairwise.consistency import confirmed_scans
    from mvreg.pairwise.search import confirm_weak_scans

    _, scales, pre, truth = views
    results = align_pairs(pre, [(0, 1), (0, 2), (1, 2)], AlignConfig(), 0, scales=scales)
    assert all(r.accepted for r in results)
    assert confirmed_scans(pre, results, scales=scales) == {0, 1, 2}
    quick = SearchConfig(weak_scans=True, screen_source_points=100, screen_iterations=2)
    same = confirm_weak_scans(pre, results, AlignConfig(), quick, scales=scales)
    assert all(a is b for a, b in zip(same, results, strict=True))

    flip = make_transform(Rotation.from_euler("x", 180, degrees=True).as_matrix(), np.zeros(3))
    broken = [
        replace(r, T_i_j=r.T_i_j @ flip, accepted=False, reason="test") if 1 in (r.i, r.j) else r
        for r in results
    ]
    assert confirmed_scans(pre, broken, scales=scales) == set()
    fixed = confirm_weak_scans(pre, broken, AlignConfig(), quick, scales=scales)
    assert confirmed_scans(pre, fixed, scales=scales) == {0, 1, 2}
    assert fixed[0].accepted and fixed[0].stats["search"]
    rot, trans = _errors(fixed[0].T_i_j, truth)
    assert rot < 0.3 and trans < 0.003
    assert fixed[1] is broken[1]  # (0, 2) was never rejected
    assert fixed[2].accepted and fixed[2].stats["search"]
    # A rejected pair whose result already is the rotation search's is not searched again
    # (the search is deterministic: it would give the same).
    searched = [replace(fixed[0], accepted=False, reason="test"), broken[1], broken[2]]
    again = confirm_weak_scans(pre, searched, AlignConfig(), quick, scales=scales)
    assert again[0] is searched[0]


def test_the_second_pass_searches_only_scans_the_first_left_unverified(views):
    """``UnorderedMode.recover``: with ``search.weak_scans`` the rejected pairs of a scan
    the first pass left without a pose are searched again, and the pair found is right;
    nothing is searched (None) when every scan was verified, when the scan's pose was found
    undetermined (a symmetry more pairs cannot settle), or with the setting off."""
    from dataclasses import replace
    from types import SimpleNamespace

    from mvreg.config import load_config
    from mvreg.globalstage.verify import ScanVerification
    from mvreg.pipeline.stages import UnorderedMode

    _, scales, pre, truth = views
    results = align_pairs(pre, [(0, 1), (0, 2), (1, 2)], AlignConfig(), 0, scales=scales)
    flip = make_transform(Rotation.from_euler("x", 180, degrees=True).as_matrix(), np.zeros(3))
    broken = [
        replace(r, T_i_j=r.T_i_j @ flip, accepted=False, reason="test") if 1 in (r.i, r.j) else r
        for r in results
    ]
    cfg = load_config(
        **{"search.weak_scans": True, "search.joint": False,
           "search.screen_source_points": 100, "search.screen_iterations": 2}
    )  # fmt: skip
    run = SimpleNamespace(cfg=cfg, local=2, timed=lambda _name: None)
    ok = ScanVerification("verified", evidence="cycle")
    mode = UnorderedMode()
    out = SimpleNamespace(solution=None, T_world_scan={})
    choices = mode.recover(run, pre, scales, broken, out, {0: ok, 2: ok}, [])
    assert choices is not None and len(choices) == 1
    new = choices[0]
    assert new[0].accepted and new[0].stats["search"]
    rot, trans = _errors(new[0].T_i_j, truth)
    assert rot < 0.3 and trans < 0.003
    assert new[1] is broken[1]
    assert mode.recover(run, pre, scales, broken, out, {0: ok, 1: ok, 2: ok}, []) is None
    open_ = ScanVerification("undetermined")
    assert mode.recover(run, pre, scales, broken, out, {0: ok, 1: open_, 2: ok}, []) is None
    off = SimpleNamespace(cfg=load_config(**{"search.joint": False}), local=2, timed=lambda _: 0)
    assert mode.recover(off, pre, scales, broken, out, {0: ok, 2: ok}, []) is None
