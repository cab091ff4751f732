"""Robust weighting of pairs around the global solve.

- :func:`cycle_check`: before the first solve, accepted pairs contradicted by cycles of 3-4
  pairs start at weight 0 (:mod:`mvreg.pairwise.consistency`).
- :func:`robust_rounds`: after it, each pair's residual under the global poses gives its
  weight (Geman-McClure-like, see ``RobustConfig``), re-solved until the weights settle;
  a pair that alone links a scan to the rest is never zeroed here (:func:`keep_connected`).
- :func:`final_check`: after refinement, an accepted pair whose own pose disagrees with
  the final poses by more than ``final_disagreement_voxels`` is listed as bad.

Every function takes its config section and the lengths of the run (``voxel``, data
units) as plain values. History of these rules: docs/design/globalstage.md.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mvreg.config.align import AlignConfig
from mvreg.config.robust import RobustConfig
from mvreg.geometry import invert_transform, transform_points
from mvreg.globalstage.solve import GlobalSolution, TrackSolver
from mvreg.pairwise import PreprocessedScan, Tracks
from mvreg.pairwise.consistency import inconsistent_pairs


def pair_residuals(tracks: Tracks, T_world_scan: dict[int, np.ndarray]) -> np.ndarray:
    """(P,) median world distance between each pair's linked points (nan: pair unused)."""
    out = np.full(len(tracks.pairs), np.nan)
    if len(tracks.link_obs) == 0:
        return out
    a, b = tracks.link_obs[:, 0], tracks.link_obs[:, 1]
    sa, sb = tracks.obs_scan[a], tracks.obs_scan[b]
    posed = np.array(sorted(int(s) for s in T_world_scan), dtype=np.int64)
    ok = np.isin(sa, posed) & np.isin(sb, posed)
    if not np.any(ok):
        return out
    pa = _world(tracks.coords, a[ok], sa[ok], T_world_scan)
    pb = _world(tracks.coords, b[ok], sb[ok], T_world_scan)
    dist = np.linalg.norm(pa - pb, axis=1)
    pair = tracks.link_pair[ok]
    for p, idx in _groups(pair):  # one pass over the links, not one per pair
        out[p] = float(np.median(dist[idx]))
    return out


def _groups(keys: np.ndarray):
    """(key, indices of that key in their order) for each distinct key, ascending."""
    order = np.argsort(keys, kind="stable")
    k = keys[order]
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]]) if len(k) else np.zeros(0, np.int64)
    return zip(k[starts].tolist(), np.split(order, starts[1:]), strict=True)


def _world(coords, obs, scan, T_world_scan) -> np.ndarray:
    """World points of observations ``obs`` of scans ``scan`` (each under its pose)."""
    out = np.empty((len(obs), 3))
    for s, idx in _groups(scan):
        out[idx] = transform_points(T_world_scan[int(s)], coords[obs[idx]])
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

    A right pair that is a scan's only link can be zeroed together with a wrong one
    nearby; without it the scan would drop out of the solve for good. Whether such a
    scan's pose is right is decided later, by verification, not here.
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
    cfg: RobustConfig,
    solver: TrackSolver,
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
    for k in range(cfg.rounds):
        res = pair_residuals(sol.tracks, sol.T_world_scan)
        new = robust_weights(res, voxel, cfg)
        new[fixed] = 0.0
        new = keep_connected(tracks.pairs, weights, new, res, cfg.zero_weight)
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
        sol = solver(tracks.reweighted(weights), init=sol.T_world_scan)
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


def cycle_check(
    pre: Sequence[PreprocessedScan], results: Sequence, cfg: RobustConfig, align: AlignConfig
) -> tuple[np.ndarray, list[dict]]:
    """Initial weights (A,) of the A accepted pairs, in the order of ``results``: 0 for
    those the cycle check sets aside; and its log (empty when it is off)."""
    accepted = [k for k, r in enumerate(results) if r.accepted]
    w0 = np.ones(len(accepted))
    if cfg.cycle_check_voxels is None:
        return w0, []
    out = inconsistent_pairs(pre, results, cfg.cycle_check_voxels, align_cfg=align)
    position = {k: n for n, k in enumerate(accepted)}
    for k, _ in out:
        w0[position[k]] = 0.0
    log = {
        "cycle_check": True,
        "limit_voxels": cfg.cycle_check_voxels,
        "pairs_zeroed": [{"scans": list(results[k].names), **info} for k, info in out],
    }
    return w0, [log]


def final_check(
    pre: Sequence[PreprocessedScan],
    results: Sequence,
    tracks: Tracks,
    weights: np.ndarray,
    sol: GlobalSolution,
    voxel: float,
    cfg: RobustConfig,
) -> tuple[np.ndarray, dict | None]:
    """Pair weights (P,) with 0 for accepted pairs whose own pose disagrees with the final
    poses by more than ``cfg.final_disagreement_voxels``, and its log (None when off)."""
    limit = cfg.final_disagreement_voxels
    if limit is None:
        return weights, None
    dis = pair_disagreements(pre, results, sol.T_world_scan, voxel)
    weights = np.array(weights, dtype=np.float64)
    index = {(int(i), int(j)): p for p, (i, j) in enumerate(tracks.pairs)}
    zeroed = []
    for (i, j), d in dis.items():
        p = index.get((i, j))
        if p is not None and weights[p] > 0 and d > limit * voxel:
            weights[p] = 0.0
            zeroed.append({"scans": [pre[i].name, pre[j].name], "voxels": d / voxel})
    return weights, {"final_check": True, "limit_voxels": limit, "pairs_zeroed": zeroed}
