"""Several hypotheses per pair, chosen jointly by agreement around cycles
(mvreg.pairwise.joint), and the batched ICP the rotation search screens with."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mvreg.config import AlignConfig, load_config
from mvreg.geometry import invert_transform, make_transform, rotation_angle_deg, transform_points
from mvreg.io.loaders import Scan
from mvreg.pairwise import (
    align_pairs,
    derive_scales,
    icp_point_to_plane,
    preprocess_all,
    with_noise,
)
from mvreg.pairwise.icp import feature_level_tree, icp_point_to_plane_batch
from mvreg.pairwise.joint import accepted_hypotheses, joint_choice

N = 5


@pytest.fixture(scope="module")
def ring():
    """Five views of the built-in object (size 1), 25 deg apart, each in a random frame; the
    pairs feature matching accepts (all right), and the truth T_i_j per pair."""
    trimesh = pytest.importorskip("trimesh")
    from data_synth.builtin import builtin_object

    mesh = builtin_object(1, subdivisions=4)
    points, faces = trimesh.sample.sample_surface(mesh, 40000, seed=5)
    normals = np.asarray(mesh.face_normals)[faces]
    rng = np.random.default_rng(11)
    frames, scans = [], []
    for k in range(N):
        a = np.radians(25.0 * k)
        d = np.array([np.cos(a), np.sin(a), 0.3])
        keep = normals @ (d / np.linalg.norm(d)) > 0.1
        F = make_transform(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
        local = transform_points(F, points[keep])
        local += np.random.default_rng(k).normal(scale=1e-4, size=local.shape)
        frames.append(F)
        scans.append(Scan(name=f"v{k}.npy", path=Path(f"v{k}.npy"), points=local))
    scales = derive_scales(scans)
    pre = preprocess_all(scans, scales.voxel, executor=2)
    scales = with_noise(scales, pre)
    pairs = [(i, j) for i in range(N) for j in range(i + 1, N)]
    results = [r for r in align_pairs(pre, pairs, AlignConfig(), 0, scales=scales) if r.accepted]
    assert len(results) >= 7  # all but the views 75 deg or more apart
    truth = {(i, j): frames[i] @ invert_transform(frames[j]) for i, j in pairs}
    return pre, scales, results, truth


def _turned(T, pre_j, deg, axis):
    """T_i_j with scan j turned by ``deg`` about ``axis`` through its centroid first."""
    c = pre_j.points.mean(axis=0)
    R = Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float)).as_matrix()
    return T @ make_transform(R, c - R @ c)


def _err(T, truth):
    return float(rotation_angle_deg((invert_transform(truth) @ T)[None, :3, :3])[0])


def _hidden(r, wrong):
    """The pair keeping a wrong pose, its right one only among its accepted hypotheses."""
    right = (r.T_i_j, {"overlap_ratio": r.overlap_ratio, **_scores(r)})
    return replace(r, T_i_j=wrong, stats={**r.stats, "accepted_hypotheses": [(wrong, None), right]})


def _scores(r):
    keys = ("inlier_rmse", "num_correspondences", "fitness", "residual_ratio")
    out = {k: getattr(r, k) for k in keys}
    out.update(free_space_violation=r.free_space_violation, unseen_violation=r.unseen_violation)
    return out


def test_the_hypotheses_that_agree_around_cycles_are_chosen(ring):
    """Every pair keeps a pose turned 70-110 deg (a different turn per pair, so no two
    agree) with the right pose second among its hypotheses: the choice puts all five scans
    in one set, and every pair comes back accepted at its right pose (< 0.3 deg)."""
    pre, scales, results, truth = ring
    assert all(r.accepted and _err(r.T_i_j, truth[(r.i, r.j)]) < 0.3 for r in results)
    axes = np.random.default_rng(3).normal(size=(len(results), 3))
    broken = [
        _hidden(r, _turned(r.T_i_j, pre[r.j], 70 + 4 * k, axes[k] / np.linalg.norm(axes[k])))
        for k, r in enumerate(results)
    ]
    hyp = {(r.i, r.j): accepted_hypotheses(r) for r in broken}
    chosen, sets = joint_choice(pre, broken, hyp, {}, scales.voxel, fine_voxel=scales.fine_voxel)
    assert [sorted(s) for s in sets] == [list(range(N))]
    for r in chosen:
        assert r.accepted and _err(r.T_i_j, truth[(r.i, r.j)]) < 0.3, (r.i, r.j)
        assert r.stats.get("joint_choice")


def test_a_scan_only_one_pair_places_is_left_as_it_was(ring):
    """Scan 4's pairs hold only wrong turns but with scan 3: no two of its pairs agree, so it
    is not placed and its pairs come back untouched; the four others are chosen right.
    From anchors (the truth of scans 0 and 1), the set starts at the anchors' poses."""
    pre, scales, results, truth = ring
    broken = []
    for k, r in enumerate(results):
        wrong = _turned(r.T_i_j, pre[r.j], 90 + 7 * k, [0, 0, 1])
        if 4 in (r.i, r.j) and r.i != 3:
            broken.append(replace(r, T_i_j=wrong, stats={"accepted_hypotheses": [(wrong, None)]}))
        else:
            broken.append(_hidden(r, wrong))
    hyp = {(r.i, r.j): accepted_hypotheses(r) for r in broken}
    chosen, sets = joint_choice(pre, broken, hyp, {}, scales.voxel, fine_voxel=scales.fine_voxel)
    assert [sorted(s) for s in sets] == [[0, 1, 2, 3]]
    for r, b in zip(chosen, broken, strict=True):
        if 4 in (r.i, r.j):
            assert r is b
        else:
            assert r.accepted and _err(r.T_i_j, truth[(r.i, r.j)]) < 0.3

    anchors = {0: np.eye(4), 1: truth[(0, 1)]}
    _, sets = joint_choice(pre, broken, hyp, anchors, scales.voxel)
    assert sorted(sets[0]) == [0, 1, 2, 3]
    np.testing.assert_array_equal(sets[0][1], truth[(0, 1)])
    assert _err(sets[0][2], truth[(0, 2)]) < 0.3


def test_a_turn_two_pairs_agree_on_that_contradicts_the_placed_views_is_passed_over(ring):
    """Scan 4's pairs (with scans 1, 2 and 3) all keep the same 90 deg turn of it, so the
    turn closes cycles; its right pose is only pair 3-4's second hypothesis. On agreement
    alone the turn is chosen. With the views' free-space tests the turned scan contradicts
    the others' views, so it is passed over (and no triangle holding it starts a set);
    scan 4's one right pair places it, but no cycle closes through it, so it stays out and
    its pairs come back as they were; the four others are chosen at their right poses."""
    pre, scales, results, truth = ring
    broken = []
    for r in results:
        wrong = _turned(r.T_i_j, pre[r.j], 90, [0, 0, 1]) if r.j == 4 else r.T_i_j
        if r.j == 4 and r.i != 3:
            broken.append(replace(r, T_i_j=wrong, stats={"accepted_hypotheses": [(wrong, None)]}))
        else:
            broken.append(_hidden(r, wrong) if r.j == 4 else r)
    assert {(r.i, r.j) for r in broken if r.j == 4} == {(1, 4), (2, 4), (3, 4)}
    hyp = {(r.i, r.j): accepted_hypotheses(r) for r in broken}

    _, sets = joint_choice(pre, broken, hyp, {}, scales.voxel, fine_voxel=scales.fine_voxel)
    assert sorted(sets[0]) == list(range(N))
    turned = invert_transform(sets[0][0]) @ sets[0][4]
    assert _err(turned, truth[(0, 4)]) > 80.0  # agreement alone: the turn

    views = (AlignConfig(), scales)
    chosen, sets = joint_choice(
        pre, broken, hyp, {}, scales.voxel, fine_voxel=scales.fine_voxel, views=views
    )
    assert [sorted(s) for s in sets] == [[0, 1, 2, 3]]
    for k in range(1, 4):
        assert _err(invert_transform(sets[0][0]) @ sets[0][k], truth[(0, k)]) < 0.3, k
    for r, b in zip(chosen, broken, strict=True):
        if r.j == 4:
            assert r is b
        else:
            assert r.accepted and _err(r.T_i_j, truth[(r.i, r.j)]) < 0.3, (r.i, r.j)


def test_the_second_pass_chooses_jointly_from_the_verified_scans(ring):
    """``UnorderedMode.recover`` with ``search.joint`` (the default): scan 2, which the first
    pass left unverified, gets its pairs chosen jointly with the verified scans 0, 1, 3, 4
    as anchors, at its right pose; nothing happens when every scan was verified or with
    the search off."""
    from mvreg.globalstage.verify import ScanVerification
    from mvreg.pipeline.stages import UnorderedMode

    pre, scales, results, truth = ring
    broken = [
        _hidden(r, _turned(r.T_i_j, pre[r.j], 120, [1, 0, 0])) if 2 in (r.i, r.j) else r
        for r in results
    ]
    poses = {0: np.eye(4), **{k: truth[(0, k)] for k in range(1, N)}}
    out = SimpleNamespace(solution=True, T_world_scan=poses)
    quick = {"search.screen_source_points": 100, "search.screen_iterations": 2}
    run = SimpleNamespace(cfg=load_config(**quick), local=2, timed=lambda _name: None)
    ok = ScanVerification("verified", evidence="cycle")
    ver = {s: ok for s in (0, 1, 3, 4)}
    mode = UnorderedMode()
    choices = mode.recover(run, pre, scales, broken, out, ver, [])
    assert choices  # on agreement alone and with the views' tests: the same choice here
    for new in choices:
        for r in new:
            assert r.accepted and _err(r.T_i_j, truth[(r.i, r.j)]) < 0.3, (r.i, r.j)
    assert mode.recover(run, pre, scales, broken, out, {**ver, 2: ok}, []) is None
    off = SimpleNamespace(
        cfg=load_config(**{"search.enabled": False}), local=2, timed=lambda _name: None
    )
    assert mode.recover(off, pre, scales, broken, out, ver, []) is None


def test_scans_left_outside_the_anchored_set_get_their_pairs_with_it_searched(ring, monkeypatch):
    """Scans 3 and 4 are right with each other, but every pair of theirs with the verified
    scans 0, 1 and 2 keeps only a 90 deg turn. Each one's nearest pair by descriptor is
    3-4 (``search.joint_partners`` 1), so the first search joins neither to the anchors;
    the search that follows tries each one's nearest pair with the anchored set (2-3 and
    2-4), and both scans are placed at their right poses, their turned pairs rejected."""
    import mvreg.pairwise.candidates as candidates
    import mvreg.pairwise.joint as joint

    pre, scales, results, truth = ring
    broken = []
    for r in results:
        if r.j in (3, 4) and r.i < 3:
            wrong = _turned(r.T_i_j, pre[r.j], 90, [0, 0, 1])
            broken.append(replace(r, T_i_j=wrong, stats={"accepted_hypotheses": [(wrong, None)]}))
        else:
            broken.append(r)
    place = {0: 0.0, 1: 1.0, 2: 2.0, 3: 10.0, 4: 10.5}
    by_name = {p.name: np.array([place[k]]) for k, p in enumerate(pre)}
    monkeypatch.setattr(candidates, "global_descriptor", lambda p: by_name[p.name])
    searched = []
    original = joint.search_hypotheses

    def spy(pre_, results_, pairs, *a, **k):
        searched.append(list(pairs))
        return original(pre_, results_, pairs, *a, **k)

    monkeypatch.setattr(joint, "search_hypotheses", spy)
    cfg = load_config(
        **{"search.joint_partners": 1, "search.screen_source_points": 100,
           "search.screen_iterations": 2}
    )  # fmt: skip
    anchors = {0: np.eye(4), 1: truth[(0, 1)], 2: truth[(0, 2)]}
    _, new = joint.choose_jointly(
        pre, broken, [3, 4], anchors, cfg.align, cfg.search, 2, scales,
        cfg.robust.cycle_check_voxels or 2.0,
    )  # fmt: skip
    assert searched == [[(3, 4)], [(2, 3), (2, 4)]]
    for r in new:
        if r.i < 3 and r.j in (3, 4) and (r.i, r.j) not in ((2, 3), (2, 4)):
            assert not r.accepted, (r.i, r.j)
        else:
            assert r.accepted and _err(r.T_i_j, truth[(r.i, r.j)]) < 0.3, (r.i, r.j)


def test_batched_icp_ends_where_icp_from_each_start_ends(ring):
    """From 12 starts 5-25 deg off, the batched ICP and the one-start ICP agree within
    0.01 deg on every start (the same Gauss-Newton steps)."""
    pre, scales, results, truth = ring
    pi, pj = pre[0], pre[1]
    rng = np.random.default_rng(2)
    starts = []
    for k in range(12):
        axis = rng.normal(size=3)
        starts.append(_turned(truth[(0, 1)], pj, 5 + 20 * k / 11, axis / np.linalg.norm(axis)))
    tree = feature_level_tree(pi)
    v = scales.voxel
    args = (pj.points, pj.normals, pi.points, pi.normals, tree)
    batch = icp_point_to_plane_batch(*args, np.stack(starts), 4 * v, 30, 0.5, 2)
    for T0, B in zip(starts, batch, strict=True):
        one = icp_point_to_plane(*args, T0, 4 * v, 30, 0.5)
        assert _err(B, one) < 0.01
    assert np.median([_err(B, truth[(0, 1)]) for B in batch]) < 1.0


def test_a_pair_the_rotation_search_already_gave_is_not_searched_again(ring, monkeypatch):
    """search_hypotheses skips a pair whose result is the rotation search's (as
    connect_unconnected leaves it): the same hypotheses as searching it again, no search."""
    from mvreg.config import SearchConfig
    from mvreg.pairwise.aligners.rotation_search import RotationSearchAligner, search_pair
    from mvreg.pairwise.joint import search_hypotheses

    pre, scales, _, _ = ring
    cfg, search = AlignConfig(), SearchConfig()
    found = search_pair(pre[0], pre[1], cfg, search, 0, 1, executor=1, scales=scales)
    assert found.stats["search"] and accepted_hypotheses(found)  # a pose was found
    unmarked = replace(found, stats={k: v for k, v in found.stats.items() if k != "search"})
    again = search_hypotheses(pre, [unmarked], [(0, 1)], cfg, search, 1, scales=scales)
    calls = []
    original = RotationSearchAligner.align
    monkeypatch.setattr(
        RotationSearchAligner,
        "align",
        lambda self, *a, **k: calls.append(1) or original(self, *a, **k),
    )
    skipped = search_hypotheses(pre, [found], [(0, 1)], cfg, search, 1, scales=scales)
    assert calls == []
    assert list(skipped) == list(again) == [(0, 1)]
    assert len(skipped[(0, 1)]) == len(again[(0, 1)])
    for (A, _), (B, _) in zip(skipped[(0, 1)], again[(0, 1)], strict=True):
        np.testing.assert_array_equal(A, B)
