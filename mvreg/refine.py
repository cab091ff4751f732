"""Stages 6 and 7: robust re-weighting of pairs and multiview ICP refinement.

Refinement, fandisk (CAD part, large planar faces; seed 1, 0.2% noise): nearest-neighbour
correspondences under the global poses left rotation errors up to 0.41 deg and origin
errors up to 0.97% of the diagonal after three rounds (0.46 deg / 1.07% before them):
along a face, samples of two scans look alike wherever they slide, so the rounds barely
move. By default each overlapping pair is first refined by point-to-plane ICP from its
relative pose under the global poses and matched under that pose.

Tried and not kept: encoding each pair's refined pose exactly (midpoints of its matched
couples, two-observation tracks) did better on fandisk and the teapot but doubled the
rotation errors on smooth shapes (builtin object 0.20 deg against 0.15 before; cow 0.11
against 0.04 with the kept variant); degeneracy-aware ICP steps (eigenvalue cut-off of the
normal matrix) left the rounds stuck where they started.

Both re-solve the global problem warm-started from the current rotations.

The rounds still average each pair's own drift along the directions its overlap leaves
free; the joint point-to-plane ICP that follows them (:mod:`mvreg.joint_icp`) removes it.
Also tried there (fandisk seed 4): moving each matched couple onto the tangent plane
(point-to-projection tracks, still a certified REG problem) converges to the same poses
but gained only 5-10% per round (0.224 -> 0.149 deg after 8 rounds), against 0.048 deg
after 7 Gauss-Newton iterations.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial

import numpy as np

from mvreg.config import RegisterConfig, RobustConfig
from mvreg.executor import single_threaded_blas
from mvreg.geometry import invert_transform, transform_points
from mvreg.pairwise import PreprocessedScan, Tracks, mutual_correspondences
from mvreg.pairwise.icp import icp_point_to_plane
from mvreg.pairwise.tracks import tracks_from_correspondences
from mvreg.solver import SolveResult, solve
from mvreg.solver.reg_admm import IterationRecord


@dataclass
class GlobalSolution:
    """Poses of the registered scans and the solve that produced them.

    T_world_scan: {scan index: (4, 4)}; the world frame is the first registered scan.
    """

    T_world_scan: dict[int, np.ndarray]
    result: SolveResult
    tracks: Tracks


def solve_tracks(
    tracks: Tracks,
    cfg: RegisterConfig,
    init: dict[int, np.ndarray] | None = None,
    callback: Callable | None = None,
) -> GlobalSolution:
    """Solve the patch problem of ``tracks``; warm start from ``init`` poses when given."""
    problem = tracks.problem
    scans = [int(s) for s in tracks.patch_scans]
    R0 = "spectral"
    if init is not None and all(s in init for s in scans):
        R0 = np.stack([init[s][:3, :3] for s in scans])
    s = cfg.solve
    res = solve(
        problem,
        s.solver,
        method=s.method,
        rho=s.rho,
        max_iter=s.max_iter,
        allow_reflections=s.allow_reflections,
        init=R0,
        seed=cfg.seed,
        callback=callback,
    )
    if callback is not None:  # one point per global solve, after its ADMM iterations
        c = res.certificate
        callback(
            IterationRecord(
                res.iterations,
                res.objective,
                c.kkt_residual if c is not None else float("nan"),
                0.0,
                res.rho_final if res.rho_final is not None else float("nan"),
            )
        )
    poses = {scan: T for scan, T in zip(scans, res.T_world_patch, strict=True)}
    return GlobalSolution(poses, res, tracks)


def pair_residuals(tracks: Tracks, T_world_scan: dict[int, np.ndarray]) -> np.ndarray:
    """(P,) median world distance between each pair's linked points (nan: pair unused)."""
    out = np.full(len(tracks.pairs), np.nan)
    if len(tracks.link_obs) == 0:
        return out
    a, b = tracks.link_obs[:, 0], tracks.link_obs[:, 1]
    sa, sb = tracks.obs_scan[a], tracks.obs_scan[b]
    ok = np.array(
        [int(x) in T_world_scan and int(y) in T_world_scan for x, y in zip(sa, sb, strict=True)]
    )
    if not np.any(ok):
        return out
    pa = np.empty((len(a), 3))
    pb = np.empty((len(a), 3))
    for s in np.unique(np.r_[sa[ok], sb[ok]]):
        T = T_world_scan[int(s)]
        ma, mb = ok & (sa == s), ok & (sb == s)
        pa[ma] = transform_points(T, tracks.coords[a[ma]])
        pb[mb] = transform_points(T, tracks.coords[b[mb]])
    dist = np.linalg.norm(pa - pb, axis=1)
    for p in np.unique(tracks.link_pair[ok]):
        sel = ok & (tracks.link_pair == p)
        out[p] = float(np.median(dist[sel]))
    return out


def robust_weights(residuals: np.ndarray, voxel: float, cfg: RobustConfig) -> np.ndarray:
    """Pair weights from residuals (see RobustConfig); unused pairs (nan) keep weight 0."""
    r = np.where(np.isfinite(residuals), residuals, np.inf)
    finite = r[np.isfinite(r)]
    if finite.size == 0:
        return np.zeros_like(r)
    c = max(cfg.scale_factor * float(np.median(finite)), cfg.min_scale_voxels * voxel)
    w = 1.0 / (1.0 + (r / c) ** 2) ** 2
    w[w < cfg.zero_weight] = 0.0
    return w


def keep_connected(
    pairs: np.ndarray, before: np.ndarray, after: np.ndarray, residuals: np.ndarray, floor: float
) -> np.ndarray:
    """``after`` with the fewest zeroed pairs restored (at weight ``floor``) that keep every
    scan connected as it was under ``before``: lowest residual first.

    A wrong pair inflates the residuals of the right pairs near it in the first solve; a
    right pair that is a scan's only link can then be zeroed together with the wrong one,
    and a scan with no weighted pair drops out of the solve for good (no pose, no residual
    to win its weight back). Fandisk, seed 4: a slid pair and the only pair of another
    scan were zeroed in the same round; that scan ended unregistered. A pair that alone
    joins two parts cannot be checked against the others anyway.
    """
    out = np.array(after, dtype=np.float64)
    parent: dict[int, int] = {}

    def find(a: int) -> int:
        parent.setdefault(a, a)
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for (i, j), w in zip(pairs, out, strict=True):
        if w > 0:
            parent[find(int(i))] = find(int(j))
    dropped = np.flatnonzero((np.asarray(before) > 0) & (out == 0))
    order = sorted(dropped, key=lambda p: (np.nan_to_num(residuals[p], nan=np.inf), p))
    for p in order:
        a, b = find(int(pairs[p][0])), find(int(pairs[p][1]))
        if a != b:
            parent[a] = b
            out[p] = floor
    return out


def robust_rounds(
    tracks: Tracks,
    sol: GlobalSolution,
    voxel: float,
    cfg: RegisterConfig,
    callback: Callable | None = None,
    weights: np.ndarray | None = None,
) -> tuple[GlobalSolution, np.ndarray, list[dict]]:
    """Iteratively re-weight pairs by their residual under the global poses and re-solve.

    ``weights``: the pair weights ``sol`` was solved with (default all 1); a pair of
    weight 0 stays at 0. Returns the final solution, the final pair weights (P,) and a log
    per round.
    """
    weights = np.ones(len(tracks.pairs)) if weights is None else np.asarray(weights, float)
    fixed = weights == 0
    log = []
    for k in range(cfg.robust.rounds):
        res = pair_residuals(sol.tracks, sol.T_world_scan)
        new = robust_weights(res, voxel, cfg.robust)
        new[fixed] = 0.0
        new = keep_connected(tracks.pairs, weights, new, res, cfg.robust.zero_weight)
        log.append(
            {
                "round": k + 1,
                "pair_residual_median": float(np.nanmedian(res))
                if np.any(np.isfinite(res))
                else None,
                "pairs_zero_weight": int(np.sum(new == 0)),
            }
        )
        if np.allclose(new, weights, atol=0.02):
            break
        weights = new
        sol = solve_tracks(
            tracks.reweighted(weights), cfg, init=sol.T_world_scan, callback=callback
        )
    return sol, weights, log


def pair_disagreements(
    pre: Sequence[PreprocessedScan],
    results: Sequence,
    T_world_scan: dict[int, np.ndarray],
    max_dist: float,
) -> dict[tuple[int, int], float]:
    """{(i, j): median distance} between where each accepted pair's own pose and the
    final poses put scan j's points that overlap scan i (within ``max_dist`` of it under
    the final poses; all of scan j's points when none do). Pairs with an unregistered scan
    are left out."""
    out = {}
    for r in results:
        if not r.accepted or r.i not in T_world_scan or r.j not in T_world_scan:
            continue
        T_final = invert_transform(T_world_scan[r.i]) @ T_world_scan[r.j]
        final = transform_points(T_final, pre[r.j].points)
        d, _ = pre[r.i].fine_tree().query(final, distance_upper_bound=max_dist)
        sel = np.isfinite(d) if np.count_nonzero(np.isfinite(d)) >= 3 else slice(None)
        own = transform_points(r.T_i_j, pre[r.j].points[sel])
        out[(r.i, r.j)] = float(np.median(np.linalg.norm(own - final[sel], axis=1)))
    return out


def overlapping_pairs(
    pre: Sequence[PreprocessedScan], T_world_scan: dict[int, np.ndarray], margin: float
) -> list[tuple[int, int]]:
    """Registered scan pairs whose world bounding boxes overlap (grown by ``margin``)."""
    boxes = {}
    for s, T in T_world_scan.items():
        w = transform_points(T, pre[s].points)
        boxes[s] = (w.min(0) - margin, w.max(0) + margin)
    keys = sorted(boxes)
    out = []
    for a_i, i in enumerate(keys):
        for j in keys[a_i + 1 :]:
            lo = np.maximum(boxes[i][0], boxes[j][0])
            hi = np.minimum(boxes[i][1], boxes[j][1])
            if np.all(lo < hi):
                out.append((i, j))
    return out


def prepare_dense_levels(scans, pre, cfg: RegisterConfig):
    """Start resampling the raw scans for the last refinement round in the background
    (it needs no poses, so it can run while the global solve does); a Future to pass to
    :func:`refine_rounds` as ``dense_levels``, or None when no round is dense."""
    if not cfg.refine.rounds or cfg.refine.dense_voxel_ratio is None or not pre:
        return None
    voxel = cfg.refine.dense_voxel_ratio * pre[0].voxel_size
    pool = ThreadPoolExecutor(1)
    future = pool.submit(_dense_levels, scans, pre, voxel, cfg.workers)
    pool.shutdown(wait=False)  # the task runs on; the pool takes no more
    return future


def _dense_levels(scans, pre, voxel: float, workers: int = 2):
    """Raw scans resampled at ``voxel``: (points, normals, KD-trees) per scan."""
    from scipy.spatial import cKDTree

    from mvreg.pairwise import resample

    def level(k):
        q, n = resample(scans[k], pre[k], voxel)
        return q, n, cKDTree(q)

    # No BLAS limit here: this may run in the background of a solve that sets its own.
    with ThreadPoolExecutor(max(1, workers)) as pool:
        out = list(pool.map(level, range(len(scans))))
    return [o[0] for o in out], [o[1] for o in out], [o[2] for o in out]


def _pair_icp(pts_i, nrm_i, tree_i, pts_j, nrm_j, T_i_j, max_dist, min_cos, max_source=3000):
    """Point-to-plane ICP of scan j onto scan i from ``T_i_j``, within ``max_dist``.

    None when the result moves some point of scan j by more than ``3 * max_dist`` (ICP
    drifting along a direction the overlap does not constrain, or into another fit).
    """
    stride = max(1, int(np.ceil(len(pts_j) / max_source)))
    src, src_n = pts_j[::stride], nrm_j[::stride]
    T = icp_point_to_plane(src, src_n, pts_i, nrm_i, tree_i, T_i_j, max_dist, 30, min_cos)
    moved = np.linalg.norm(transform_points(T, src) - transform_points(T_i_j, src), axis=1)
    return T if float(np.max(moved, initial=0.0)) <= 3.0 * max_dist else None


def _match_pair(pair, sol, points, normals, trees, max_dist, cfg, tc):
    """One pair of a refinement round: (pair, (idx_i, idx_j), distances under the global
    poses), or None when the pair has too few correspondences. The correspondences are
    the mutual nearest neighbours under the pair's ICP-refined pose (pairwise-icp) or under
    the global poses (nearest, or when ICP runs away)."""
    i, j = pair
    T_i_j = invert_transform(sol.T_world_scan[i]) @ sol.T_world_scan[j]
    T_match = None
    if cfg.refine.correspondences == "pairwise-icp":
        T_match = _pair_icp(
            points[i], normals[i], trees[i], points[j], normals[j], T_i_j, max_dist,
            tc.min_normal_cos,
        )  # fmt: skip
    T_match = T_i_j if T_match is None else T_match
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
    if len(idx_i) < cfg.refine.min_correspondences:
        return None
    # Residuals under the global poses: a pair whose own optimum disagrees with them
    # shows it in its robust weight.
    moved = transform_points(T_i_j, points[j][idx_j])
    return (i, j), (idx_i, idx_j), np.linalg.norm(points[i][idx_i] - moved, axis=1)


def refine_rounds(
    pre: Sequence[PreprocessedScan],
    sol: GlobalSolution,
    cfg: RegisterConfig,
    callback: Callable | None = None,
    scans: Sequence | None = None,
    pairs: Sequence[tuple[int, int]] | None = None,
    tracks_cfg=None,
    dense_levels=None,
) -> tuple[GlobalSolution, list[dict]]:
    """Multiview ICP: correspondences of all overlapping scans under the global poses,
    tracks, global re-solve warm-started; ``cfg.refine.rounds`` times, shrinking distance.

    With ``scans`` and ``cfg.refine.dense_voxel_ratio``, the last round matches the raw
    scans resampled at that fraction of the feature voxel instead of the fine points.
    ``pairs`` restricts the rounds to those scan pairs (default: every registered pair
    whose world bounding boxes overlap); ``tracks_cfg`` overrides ``cfg.tracks`` (normal
    agreement, per-pair thinning, conflict splitting). ``dense_levels``: the Future of
    :func:`prepare_dense_levels` for the same scans (else resampled here).

    With ``cfg.refine.correspondences == "pairwise-icp"`` (default) each pair is first
    refined by point-to-plane ICP from its relative pose under the global poses
    (:func:`_pair_icp`, run on ``cfg.workers`` threads) and matched under that
    pose (a pair whose ICP runs away is matched under the global poses). Residuals for the
    robust weights are measured under the global poses, so a pair whose refined pose
    disagrees with the rest is down-weighted.
    """
    tc = tracks_cfg if tracks_cfg is not None else cfg.tracks
    log = []
    voxel = pre[0].voxel_size
    names = [p.name for p in pre]
    rounds = cfg.refine.rounds
    for k in range(rounds):
        dist_v = cfg.refine.distance_voxels[min(k, len(cfg.refine.distance_voxels) - 1)]
        dense = k == rounds - 1 and scans is not None and cfg.refine.dense_voxel_ratio is not None
        if dense and dense_levels is not None:
            points, normals, trees = dense_levels.result()
        elif dense:
            points, normals, trees = _dense_levels(
                scans, pre, cfg.refine.dense_voxel_ratio * voxel, cfg.workers
            )
        else:
            points = [p.fine_points for p in pre]
            normals = [p.fine_normals for p in pre]
            trees = [p.fine_tree() for p in pre]
        candidates = (
            overlapping_pairs(pre, sol.T_world_scan, dist_v * voxel)
            if pairs is None
            else [(i, j) for i, j in pairs if i in sol.T_world_scan and j in sol.T_world_scan]
        )

        match = partial(
            _match_pair, sol=sol, points=points, normals=normals, trees=trees,
            max_dist=dist_v * voxel, cfg=cfg, tc=tc,
        )  # fmt: skip
        used, corr, dists = [], [], []
        with single_threaded_blas(), ThreadPoolExecutor(cfg.workers) as pool:
            for out in pool.map(match, candidates):
                if out is not None:
                    used.append(out[0])
                    corr.append(out[1])
                    dists.append(out[2])
        if not used:
            break
        pairs_arr = np.array(used, dtype=np.int64)
        # Robust weights per pair from its residual under the current poses.
        med = np.array([float(np.median(d)) for d in dists])
        w = robust_weights(med, voxel, cfg.robust)
        tracks = tracks_from_correspondences(
            points, names, pairs_arr, corr, w, distances=dists,
            split_conflicts=tc.split_conflicting_tracks,
        )  # fmt: skip
        if tracks.problem is None:
            break
        prev = sol
        sol = solve_tracks(tracks, cfg, init=sol.T_world_scan, callback=callback)
        moved_max = max(
            float(np.linalg.norm(sol.T_world_scan[s][:3, 3] - prev.T_world_scan[s][:3, 3]))
            for s in sol.T_world_scan
            if s in prev.T_world_scan
        )
        log.append(
            {
                "round": k + 1,
                "distance_voxels": dist_v,
                "dense": bool(dense),
                "pairs": len(used),
                "observations": int(tracks.problem.num_observations),
                "pair_residual_median": float(np.median(med)),
                "max_translation_change": moved_max,
                "certified": sol.result.certified,
            }
        )
    return sol, log
