"""Multiview refinement rounds: correspondences between all overlapping scans recomputed
under the current global poses, then a warm-started global re-solve.

Takes the preprocessed scans, a :class:`GlobalSolution`, the ``refine``, ``robust`` and
``tracks`` sections, the feature voxel (data units), a :class:`TrackSolver` and an
executor; returns the refined solution and a log per round. Each overlapping pair is
first refined by point-to-plane ICP from its relative pose under the global poses and
matched under that pose (``correspondences="pairwise-icp"``), so the rounds move along
planes as far as the other faces require. Why, and what else was tried:
docs/design/globalstage.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial

import numpy as np

from mvreg.config.refine import RefineConfig
from mvreg.config.robust import RobustConfig
from mvreg.config.tracks import TracksConfig
from mvreg.executor import Executor
from mvreg.geometry import invert_transform, transform_points
from mvreg.globalstage.robust import robust_weights
from mvreg.globalstage.scan_model import cell_sharing
from mvreg.globalstage.solve import GlobalSolution, TrackSolver, max_translation_change
from mvreg.pairwise import PreprocessedScan, mutual_correspondences, resample
from mvreg.pairwise.icp import icp_point_to_plane_many
from mvreg.pairwise.tracks import tracks_from_correspondences

MAX_PARTNERS = 12
"""A scan is matched in the refinement rounds with at most this many others of its own
choosing (its largest overlaps), so the rounds' pairs grow with the scans, not with their
square (issue 14: 40 builtin scans, 269 pairs a round instead of 657; 80 scans, 579
instead of 2681; accuracy kept with the joint ICP's wider choice)."""


def overlapping_pairs(
    pre: Sequence[PreprocessedScan],
    T_world_scan: dict[int, np.ndarray],
    margin: float,
    max_partners: int | None = MAX_PARTNERS,
) -> list[tuple[int, int]]:
    """Registered scan pairs whose world bounding boxes overlap (grown by ``margin``),
    sorted. A scan with more than ``max_partners`` such pairs keeps those to the
    ``max_partners`` scans that share the most of its surface (cells of twice ``margin``
    occupied by both, as a fraction of the smaller scan's cells); a pair is kept when
    either scan keeps it, so at most ``max_partners`` pairs per scan are chosen in all.
    None (or ``margin`` 0): every pair."""
    keys = sorted(T_world_scan)
    world = [transform_points(T_world_scan[s], pre[s].points) for s in keys]
    lo = np.array([w.min(0) - margin for w in world]).reshape(-1, 3)
    hi = np.array([w.max(0) + margin for w in world]).reshape(-1, 3)
    over = np.all(np.maximum(lo[:, None], lo[None]) < np.minimum(hi[:, None], hi[None]), axis=2)
    np.fill_diagonal(over, False)
    if max_partners is not None and margin > 0 and len(keys) and over.sum(1).max() > max_partners:
        over &= _closest_partners(world, over, 2.0 * margin, max_partners)
    a, b = np.nonzero(np.triu(over, 1))
    return [(keys[x], keys[y]) for x, y in zip(a.tolist(), b.tolist(), strict=True)]


def _closest_partners(world, over: np.ndarray, cell: float, k: int) -> np.ndarray:
    """(n, n) bool: (a, b) when b is among the k candidates (``over``) of a that share
    the largest fraction of occupied cells, or a among those of b (ties: lower index)."""
    shared, size = cell_sharing(world, cell)
    frac = shared / np.maximum(np.minimum(size[:, None], size[None]), 1.0)
    keep = np.zeros_like(over)
    for a in range(len(world)):
        cand = np.flatnonzero(over[a])
        keep[a, cand[np.lexsort((cand, -frac[a, cand]))[:k]]] = True
    return keep | keep.T


def prepare_dense_levels(
    scans, pre, cfg: RefineConfig, voxel: float, workers: int
) -> Future | None:
    """Start resampling the raw scans for the last refinement round in the background
    (it needs no poses, so it can run while the global solve does); a Future to pass to
    :func:`refine_rounds` as ``dense_levels``, or None when no round is dense."""
    if not cfg.rounds or cfg.dense_voxel_ratio is None or not pre:
        return None
    pool = ThreadPoolExecutor(1)
    future = pool.submit(dense_levels, scans, pre, cfg.dense_voxel_ratio * voxel, workers)
    pool.shutdown(wait=False)  # the task runs on; the pool takes no more
    return future


def dense_levels(scans, pre, voxel: float, workers: int = 2):
    """Raw scans resampled at ``voxel``: (points, normals, KD-trees) per scan."""
    from scipy.spatial import cKDTree

    def level(k):
        q, n = resample(scans[k], pre[k], voxel)
        return q, n, cKDTree(q)

    # No BLAS limit here: this may run in the background of a solve that sets its own.
    with ThreadPoolExecutor(max(1, workers)) as pool:
        out = list(pool.map(level, range(len(scans))))
    return [o[0] for o in out], [o[1] for o in out], [o[2] for o in out]


def pair_icp(pts_i, nrm_i, tree_i, pts_j, nrm_j, T_i_j, max_dist, min_cos, max_source=3000):
    """Point-to-plane ICP of scan j onto scan i from ``T_i_j``, within ``max_dist``.

    None when the result moves some point of scan j by more than ``3 * max_dist`` (ICP
    drifting along a direction the overlap does not constrain, or into another fit).
    """
    return pair_icps(pts_i, nrm_i, tree_i, [(pts_j, nrm_j, T_i_j)], max_dist, min_cos,
                     max_source)[0]  # fmt: skip


def pair_icps(pts_i, nrm_i, tree_i, sources, max_dist, min_cos, max_source=3000) -> list:
    """:func:`pair_icp` of every (points, normals, ``T_i_j``) of ``sources`` onto scan i,
    run together (:func:`icp_point_to_plane_many`: the same poses as one at a time)."""
    src = []
    for pts_j, nrm_j, T_i_j in sources:
        stride = max(1, int(np.ceil(len(pts_j) / max_source)))
        src.append((pts_j[::stride], nrm_j[::stride], T_i_j))
    found = icp_point_to_plane_many(src, pts_i, nrm_i, tree_i, max_dist, 30, min_cos)
    kept = [_kept(T, T0, p, max_dist) for (p, _, T0), T in zip(src, found, strict=True)]
    return [T if ok else None for T, ok in zip(found, kept, strict=True)]


def match_scan(group, sol, points, normals, trees, max_dist, cfg: RefineConfig, tc: TracksConfig):
    """Every pair (i, j) of ``group`` = (i, [j, ...]) of a refinement round, in that order:
    (pair, (idx_i, idx_j), distances under the global poses), or None when the pair has
    too few correspondences. The correspondences are the mutual nearest neighbours under
    the pair's ICP-refined pose (pairwise-icp: :func:`pair_icps`, the ICPs onto scan i run
    together) or under the global poses (nearest, or when ICP runs away)."""
    i, js = group
    T_i = invert_transform(sol.T_world_scan[i])
    rel = [T_i @ sol.T_world_scan[j] for j in js]
    T_match = list(rel)
    if cfg.correspondences == "pairwise-icp":
        found = pair_icps(
            points[i], normals[i], trees[i],
            [(points[j], normals[j], T) for j, T in zip(js, rel, strict=True)],
            max_dist, tc.min_normal_cos, max_source=cfg.icp_points,
        )  # fmt: skip
        T_match = [T0 if T is None else T for T0, T in zip(rel, found, strict=True)]
    return [
        _matched(i, j, T_i_j, T_m, points, normals, trees, max_dist, cfg, tc)
        for j, T_i_j, T_m in zip(js, rel, T_match, strict=True)
    ]


def _kept(T, T0, src, max_dist) -> bool:
    """A pair ICP's result is kept unless it moves some point of the source by more than
    ``3 * max_dist`` from the start (drifting along a direction the overlap does not
    constrain, or into another fit)."""
    moved = np.linalg.norm(transform_points(T, src) - transform_points(T0, src), axis=1)
    return float(np.max(moved, initial=0.0)) <= 3.0 * max_dist


def _matched(i, j, T_i_j, T_match, points, normals, trees, max_dist, cfg, tc):
    """The mutual correspondences of (i, j) under ``T_match``, their distances under the
    global poses ``T_i_j``; None below ``cfg.min_correspondences``."""
    idx_i, idx_j = mutual_correspondences(
        points[i],
        points[j],
        T_match,
        max_dist,
        normals_i=normals[i],
        normals_j=normals[j],
        min_normal_cos=tc.min_normal_cos,
        tree_i=trees[i],
        tree_j=trees[j],
    )
    cap = tc.max_correspondences_per_pair
    if cap is not None and len(idx_i) > cap:  # evenly thinned, as in pair_correspondences
        keep = np.linspace(0, len(idx_i) - 1, cap).round().astype(np.int64)
        idx_i, idx_j = idx_i[keep], idx_j[keep]
    if len(idx_i) < cfg.min_correspondences:
        return None
    # Residuals under the global poses: a pair whose own optimum disagrees with them
    # shows it in its robust weight.
    moved = transform_points(T_i_j, points[j][idx_j])
    return (i, j), (idx_i, idx_j), np.linalg.norm(points[i][idx_i] - moved, axis=1)


def refine_rounds(
    pre: Sequence[PreprocessedScan],
    sol: GlobalSolution,
    cfg: RefineConfig,
    robust: RobustConfig,
    tracks_cfg: TracksConfig,
    voxel: float,
    solver: TrackSolver,
    executor: Executor,
    scans: Sequence | None = None,
    pairs: Sequence[tuple[int, int]] | None = None,
    dense: Future | None = None,
) -> tuple[GlobalSolution, list[dict]]:
    """Multiview ICP: correspondences of all overlapping scans under the global poses,
    tracks, global re-solve warm-started; ``cfg.rounds`` times, shrinking distance.

    With ``scans`` and ``cfg.dense_voxel_ratio``, the last round matches the raw scans
    resampled at that fraction of the feature voxel instead of the fine points
    (``dense``: the Future of :func:`prepare_dense_levels`, else resampled here).
    ``pairs`` restricts the rounds to those scan pairs (default: registered pairs whose
    world bounding boxes overlap, at most :data:`MAX_PARTNERS` chosen per scan).
    Residuals for the robust weights are measured under the global poses, so a pair whose
    refined pose disagrees with the rest is down-weighted.
    """
    log = []
    names = [p.name for p in pre]
    for k in range(cfg.rounds):
        dist_v = cfg.distance_voxels[min(k, len(cfg.distance_voxels) - 1)]
        last_dense = k == cfg.rounds - 1 and scans is not None and cfg.dense_voxel_ratio is not None
        points, normals, trees = _round_level(pre, scans, cfg, voxel, executor, last_dense, dense)
        candidates = (
            overlapping_pairs(pre, sol.T_world_scan, dist_v * voxel)
            if pairs is None
            else [(i, j) for i, j in pairs if i in sol.T_world_scan and j in sol.T_world_scan]
        )
        round_cfg = cfg
        if k == cfg.rounds - 1 and k > 0:
            round_cfg = cfg.model_copy(
                update={
                    "correspondences": cfg.last_round_correspondences,
                    "icp_points": cfg.last_round_icp_points,
                }
            )
        match = partial(
            match_scan, sol=sol, points=points, normals=normals, trees=trees,
            max_dist=dist_v * voxel, cfg=round_cfg, tc=tracks_cfg,
        )  # fmt: skip
        groups: dict[int, list[int]] = {}
        for i, j in candidates:
            groups.setdefault(i, []).append(j)
        items = list(groups.items())
        by_pair = {
            (i, j): m
            for (i, js), ms in zip(items, executor.map(match, items), strict=True)
            for j, m in zip(js, ms, strict=True)
        }
        matched = [m for p in candidates if (m := by_pair[p]) is not None]
        if not matched:
            break
        used = [m[0] for m in matched]
        dists = [m[2] for m in matched]
        # Robust weights per pair from its residual under the current poses.
        med = np.array([float(np.median(d)) for d in dists])
        tracks = tracks_from_correspondences(
            points, names, np.array(used, dtype=np.int64), [m[1] for m in matched],
            robust_weights(med, voxel, robust), distances=dists,
            split_conflicts=tracks_cfg.split_conflicting_tracks,
        )  # fmt: skip
        if tracks.problem is None:
            break
        prev = sol
        sol = solver(tracks, init=sol.T_world_scan)
        log.append(
            {
                "round": k + 1,
                "distance_voxels": dist_v,
                "dense": bool(last_dense),
                "pairs": len(used),
                "observations": int(tracks.problem.num_observations),
                "pair_residual_median": float(np.median(med)),
                "max_translation_change": max_translation_change(sol, prev),
                "certified": sol.result.certified,
            }
        )
    return sol, log


def _round_level(pre, scans, cfg: RefineConfig, voxel, executor, last_dense, dense):
    """(points, normals, KD-trees) per scan matched in a round: fine points, or the dense
    resampling of the raw scans in the last round."""
    if last_dense and dense is not None:
        return dense.result()
    if last_dense:
        return dense_levels(scans, pre, cfg.dense_voxel_ratio * voxel, executor.workers)
    return (
        [p.fine_points for p in pre],
        [p.fine_normals for p in pre],
        [p.fine_tree() for p in pre],
    )
