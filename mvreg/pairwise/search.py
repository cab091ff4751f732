"""Stage 3b: rotation search for scans that feature matching left unconnected.

FPFH needs curvature. A view of a CAD part's flat faces (the fandisk's top) has
histograms that all look alike, RANSAC gets 0-1 right matches out of hundreds, and the
scan ends up with no accepted pair although it overlaps its neighbours by 80%. Such a
scan would be reported unregistered; before that, this stage searches the rotations
directly: for each scan outside the largest connected set of accepted pairs, its
``partners`` most similar scans inside the set (pooled FPFH,
:func:`~mvreg.pairwise.candidates.global_descriptor`) are tried from ``len(starts)``
starting rotations (the 60 rotations of the icosahedral group, each also turned by
``offset_deg`` about x, y and z: 240 starts, no rotation farther than about 25 degrees
from one), centroids on centroids. Each start runs a few iterations of feature-level
point-to-plane ICP with shrinking distances on at most ``screen_source_points`` points
and must pass the loosened acceptance rule (:func:`~mvreg.pairwise.align._decide`,
including both free-space tests, which reject the slides and flips that fit the planes
locally); the distinct survivors go through the full verification of ordinary pairs,
and the best-supported accepted one is kept. The first partner that yields an accepted
pose connects the scan; the search then moves on to the next unconnected scan.

It costs about 1-2 s per partner on two cores and runs only when some scan is
unconnected, so data that feature matching handles (the real bunny) never pays for it.
Deterministic: the starts are fixed and the partners are ordered by descriptor distance.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from mvreg.config.align import AlignConfig, SearchConfig
from mvreg.executor import Executor, make_executor
from mvreg.pairwise.align import (
    PairResult,
    _decide,
    _feature_level_tree,
    _same_pose,
    _support,
    _verify,
    icp_point_to_plane,
    pair_result,
    score_alignment,
)
from mvreg.pairwise.candidates import global_descriptor
from mvreg.pairwise.preprocess import PreprocessedScan


def rotation_starts(offset_deg: float = 20.0) -> np.ndarray:
    """(240, 3, 3): the icosahedral group, and its copies turned about x, y and z."""
    group = Rotation.create_group("I").as_matrix()
    a = np.radians(offset_deg)
    turns = Rotation.from_rotvec([[0, 0, 0], [a, 0, 0], [0, a, 0], [0, 0, a]]).as_matrix()
    return np.einsum("aij,bjk->abik", group, turns).reshape(-1, 3, 3)


def search_pair(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    cfg: AlignConfig | None = None,
    search: SearchConfig | None = None,
    i: int = 0,
    j: int = 1,
    executor: Executor | int = 2,
) -> PairResult:
    """Align j to i from every start rotation (module doc); accepted or not."""
    cfg, search = cfg or AlignConfig(), search or SearchConfig()
    start = time.perf_counter()
    v = pre_i.voxel_size
    ci, cj = pre_i.points.mean(axis=0), pre_j.points.mean(axis=0)
    radius = float(np.max(np.linalg.norm(pre_j.points - cj, axis=1)))
    stride = max(1, len(pre_j.points) // search.screen_source_points)
    src, src_n = pre_j.points[::stride], pre_j.normals[::stride]
    tree = _feature_level_tree(pre_i)

    def screen(R: np.ndarray):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, ci - R @ cj
        for dist in search.screen_distances_voxels:
            T = icp_point_to_plane(
                src, src_n, pre_i.points, pre_i.normals, tree, T, dist * v,
                search.screen_iterations, cfg.icp_min_normal_cos,
            )  # fmt: skip
        scores = score_alignment(pre_i, pre_j, T, cfg, level="feature")
        return T if not _decide(scores, cfg, slack=cfg.coarse_gate_slack) else None

    screened = make_executor(executor).map(screen, rotation_starts(search.offset_deg))
    survivors = [T for T in screened if T is not None]
    distinct: list[np.ndarray] = []
    for T in survivors:
        if not any(_same_pose(T, K, v, cj, radius) for K in distinct):
            distinct.append(T)
    tried = [_verify(pre_i, pre_j, T, cfg) for T in distinct]
    passed = [t for t in tried if not t[1]]
    stats = {"search": True, "search_survivors": len(survivors), "hypotheses_tried": len(tried)}
    stats["hypotheses_accepted"] = len(passed)
    if tried:
        T, reason, scores, _ = max(passed, key=lambda t: _support(t[2], cfg), default=tried[0])
    else:
        T, reason, scores = np.eye(4), "rotation search found no alignment", None
    return pair_result(pre_i, pre_j, i, j, T, reason, scores, stats, start)


def _components(m: int, results: Sequence[PairResult]) -> np.ndarray:
    """Label of each scan's connected set under the accepted pairs."""
    parent = list(range(m))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for r in results:
        if r.accepted:
            parent[find(r.i)] = find(r.j)
    return np.array([find(a) for a in range(m)])


def connect_unconnected(
    pre: Sequence[PreprocessedScan],
    results: list[PairResult],
    cfg: AlignConfig | None = None,
    search: SearchConfig | None = None,
    progress: Callable[[PairResult], None] | None = None,
    executor: Executor | int = 2,
) -> list[PairResult]:
    """``results`` with searched pairs for scans outside the largest connected set.

    A searched pair replaces the failed result of the same pair (or is appended when the
    pair was not a candidate). Scans are visited in index order; each tries its
    ``search.partners`` nearest scans of the (growing) largest set by global descriptor.
    """
    cfg, search = cfg or AlignConfig(), search or SearchConfig()
    results = list(results)
    m = len(pre)
    if not search.enabled or m < 2:
        return results
    desc = np.stack([global_descriptor(p) for p in pre])
    index = {(r.i, r.j): k for k, r in enumerate(results)}
    for a in range(m):
        label = _components(m, results)
        sizes = np.bincount(label, minlength=m)
        main = int(np.argmax(sizes))
        if label[a] == main:
            continue
        inside = np.flatnonzero(label == main)
        order = inside[np.argsort(np.linalg.norm(desc[inside] - desc[a], axis=1), kind="stable")]
        for b in order[: search.partners]:
            i, j = (int(min(a, b)), int(max(a, b)))
            res = search_pair(pre[i], pre[j], cfg, search, i=i, j=j, executor=executor)
            if (i, j) in index:
                if res.accepted or not results[index[(i, j)]].accepted:
                    results[index[(i, j)]] = res
            else:
                index[(i, j)] = len(results)
                results.append(res)
            if progress is not None:
                progress(res)
            if res.accepted:
                break
    return results
