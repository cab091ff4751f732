"""How well a pose ``T_i_j`` fits two scans: the scores the acceptance rule reads.

Takes two preprocessed scans, a pose ``T_i_j`` (scan j into scan i's frame), the
``AlignConfig`` and the run's :class:`~mvreg.scales.Scales` (``v`` = feature voxel);
returns plain numbers. Deterministic; read-only on the scans except for cached
structures (KD-trees, depth grids). ``noise`` = mean of the two scans' own
:attr:`~mvreg.pairwise.preprocess.PreprocessedScan.noise`.

* a *neighbour* of a point is the nearest point of the other scan within
  ``score_distance_voxels * v`` whose normal agrees (cosine >= ``score_min_normal_cos``);
  its *residual* is the distance to the neighbour's tangent plane;
* ``fitness``: fraction of scan j's points with a neighbour (Open3D's meaning);
* ``residual_ratio``: median residual / noise: about 1 for a correct alignment (residuals
  like the scans' own noise), large for a wrong one pressed into contact by ICP;
* ``overlap_ratio``: fraction of the better-covered scan whose residual is at most
  ``tight_residual_ratio * noise``: the part that really coincides;
* ``inlier_rmse``: root mean square residual (data units); ``median_residual``;
* ``num_correspondences``: mutual neighbours;
* ``free_space_violation`` (:func:`free_space_violation`): for scans that are single views
  (:func:`~mvreg.pairwise.preprocess.view_direction`), the larger of the two scans'
  shares of points that, seen from the other scan's sensor direction, lie clearly in
  front of the surface the other scan measured there (it saw through empty space);
* ``unseen_violation`` (:func:`unseen_violation`): the share of points facing the other
  view's sensor where that view saw nothing at all;
* ``off_plane_matches`` (fine level, scans that surround their sensors:
  :func:`off_plane_matches`): of the scan's matches within the tight residual, how many
  lie off the plane most of them share, the more of the two scans' counts; NaN for other
  scans and when neither has ``3 * PAIR_OFF_PLANE_MATCHES`` such matches. A pose whose
  matches lie on one plane (a scene's ground) is held in heading about its normal and
  slide along it by nothing but the normals' noise.

Both view tests are NaN when either scan is not a single view (the test is skipped).
Measured values on real and synthetic scans: ``docs/design/pairwise.md``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from mvreg.config.align import AlignConfig
from mvreg.geometry import invert_transform, transform_points
from mvreg.pairwise.icp import feature_level_tree, nearest_with_normals
from mvreg.pairwise.preprocess import PreprocessedScan, scan_scales
from mvreg.pairwise.view_projection import ViewProjection, cell_keys, neighbour_keys
from mvreg.scales import Scales

OFF_PLANE_MATCHES = 10
"""Matches off a plane that hold what it leaves open (:func:`off_plane_matches`), for a
scan against the union of others (verification, placement): three in general position
fix its three motions; a few times that, so that the odd coincidental match cannot.
Measured on a scene of 60 LiDAR stations and generalization runs: wrong placements on the
ground had 0-1 (four stations and a sparse featuretype view 40% of the diagonal off),
right poses held by a little structure 5-48 (sparse machined parts 14-48)."""

PAIR_OFF_PLANE_MATCHES = 3
"""The same for one pair of scans that surround their sensors (the acceptance rule,
:mod:`mvreg.pairwise.decision`): the three that can fix those motions at all. A pair sees
less than a union: on the 60-station LiDAR scene six of the seven pairs accepted 20-170
deg off had none, the seventh 5, and the 104 right pairs at least 3 (two below 10: 3 and
6). Fewer than three and the heading and the slide are open: the pose is a guess,
whatever else fits."""


def off_plane_matches(
    pts: np.ndarray, nrm: np.ndarray, model_n: np.ndarray, voxel: float, min_count: int
) -> tuple[int, int, np.ndarray] | None:
    """(matches off the plane, matches, the plane's normal) of matched points ``pts`` with
    their own normals ``nrm`` and their matches' normals ``model_n`` (one frame), or None
    with fewer than ``3 * min_count`` matches (too few to judge: the callers' own minimum
    of matches applies). A match is off the plane when its match's normal is tilted from
    the matches' dominant normal by more than four standard deviations of a normal's tilt
    (from the matched pairs of normals: ``mean(1 - (n . n_match)^2) / 4`` per component)
    and its point lies more than ``voxel`` off the plane through the other matches: real
    structure, tilted and raised. Both conditions: estimated normals have heavy tails (a
    station placed 115 deg off on ground alone had 64 of 3408 matches beyond four
    deviations, all on the ground)."""
    n = len(pts)
    if n < 3 * min_count:
        return None
    cos = np.einsum("ij,ij->i", nrm, model_n)
    sigma = float(np.sqrt(np.mean(1.0 - cos**2) / 4.0))
    axis = np.linalg.eigh(model_n.T @ model_n)[1][:, -1]
    tilted = np.sqrt(np.clip(1.0 - (model_n @ axis) ** 2, 0.0, 1.0)) > 4.0 * sigma
    height = pts @ axis
    level = float(np.median(height[~tilted])) if np.any(~tilted) else 0.0
    off = int(np.count_nonzero(tilted & (np.abs(height - level) > voxel)))
    return off, n, axis


def _pair_off_plane(pi, ni, pj, nj, T_i_j, near_j, near_i, tight_j, tight_i, voxel) -> float:
    """``off_plane_matches`` of a pair: the larger count of the two directions (scan j's
    tight matches in i's frame, scan i's in j's); NaN when neither has enough."""
    R, t = T_i_j[:3, :3], T_i_j[:3, 3]
    sj, si = np.flatnonzero(tight_j), np.flatnonzero(tight_i)
    both = (
        (pj[sj] @ R.T + t, nj[sj] @ R.T, ni[near_j[sj]]),
        ((pi[si] - t) @ R, ni[si] @ R, nj[near_i[si]]),
    )
    counts = [off_plane_matches(p, n, m, voxel, PAIR_OFF_PLANE_MATCHES) for p, n, m in both]
    counts = [c[0] for c in counts if c is not None]
    return float(max(counts)) if counts else float("nan")


def _surrounds(pre: PreprocessedScan) -> bool:
    """Whether the scan surrounds its sensor (a spherical view: a spinning LiDAR, a
    terrestrial laser scanner). Only such pairs are asked for matches off a plane: the
    part of a plane two of them share ends at their ranges, not at an edge of the surface,
    so nothing but structure off it holds the heading and the slide. Two views of one face
    of an object share it up to the object's outline, which the overlap and the unseen
    test hold (featuretype sparse seed 0: a right pair of two views of one face, no match
    off it, overlap 0.69, 0.1 deg)."""
    view = view_projection(pre)
    return view is not None and view.spherical


def score_alignment(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    T_i_j: np.ndarray,
    cfg: AlignConfig | None = None,
    level: Literal["fine", "feature"] = "fine",
    *,
    scales: Scales | None = None,
) -> dict:
    """Quality scores of ``T_i_j`` (see the module docstring) on the fine or feature level.

    Returns a dict: fitness, overlap_ratio, residual_ratio, median_residual, inlier_rmse,
    num_correspondences, free_space_violation and unseen_violation (always on the fine
    level), off_plane_matches (NaN on the feature level and unless both scans surround
    their sensors). ``scales``: the run's (default: those ``pre_i`` was preprocessed at).
    """
    cfg = cfg or AlignConfig()
    scales = scan_scales(pre_i) if scales is None else scales
    if level == "fine":
        pi, ni, pj, nj = (
            pre_i.fine_points,
            pre_i.fine_normals,
            pre_j.fine_points,
            pre_j.fine_normals,
        )
        ti, tj = pre_i.fine_tree(), pre_j.fine_tree()
    else:
        pi, ni, pj, nj = pre_i.points, pre_i.normals, pre_j.points, pre_j.normals
        ti, tj = feature_level_tree(pre_i), feature_level_tree(pre_j)
    max_dist, cos = cfg.score_distance_voxels * scales.voxel, cfg.score_min_normal_cos
    near_j, r_j = nearest_with_normals(ti, pi, ni, pj, nj, T_i_j, max_dist, cos)
    near_i, r_i = nearest_with_normals(tj, pj, nj, pi, ni, invert_transform(T_i_j), max_dist, cos)
    has_j, has_i = near_j >= 0, near_i >= 0
    mutual = np.count_nonzero(near_i[near_j[has_j]] == np.flatnonzero(has_j))
    noise = 0.5 * (pre_i.noise + pre_j.noise)
    res = np.concatenate([r_i[has_i], r_j[has_j]])
    tight = cfg.tight_residual_ratio * noise
    median = float(np.median(res)) if len(res) else float("inf")
    off_plane = float("nan")
    if level == "fine" and _surrounds(pre_i) and _surrounds(pre_j):
        tight_j, tight_i = has_j & (r_j <= tight), has_i & (r_i <= tight)
        off_plane = _pair_off_plane(
            pi, ni, pj, nj, T_i_j, near_j, near_i, tight_j, tight_i, scales.voxel
        )  # fmt: skip
    return {
        "fitness": float(np.mean(has_j)),
        "overlap_ratio": max(float(np.mean(r_i <= tight)), float(np.mean(r_j <= tight))),
        "residual_ratio": median / noise,
        "median_residual": median,
        "inlier_rmse": float(np.sqrt(np.mean(res**2))) if len(res) else float("inf"),
        "num_correspondences": int(mutual),
        "free_space_violation": free_space_violation(pre_i, pre_j, T_i_j, cfg, scales=scales),
        "unseen_violation": unseen_violation(pre_i, pre_j, T_i_j, cfg, scales=scales),
        "off_plane_matches": off_plane,
    }


# ---------------------------------------------------------------------------- view tests


def view_projection(pre: PreprocessedScan) -> ViewProjection | None:
    """The scan's :class:`ViewProjection` (cached); None when it is not a single view."""
    if pre.view_direction is None:
        return None
    if "view_projection" not in pre._cache:
        seen = pre.fine_points if pre.view_points is None else pre.view_points
        pre._cache["view_projection"] = ViewProjection(pre.view_direction, pre.viewpoint, seen)
    return pre._cache["view_projection"]


def depth_grid(pre: PreprocessedScan, fine_voxel: float):
    """Front-most depth of the fine points per cell (1.5 fine voxels) of a grid across the
    view: (projection, cell, sorted cell keys, depths, reach: how many cells away a cell's
    front depth may come from); None without a view. For a spherical view, each point
    counts in its cell and the 26 around it (reach 2): a spinning sensor's beams lie
    farther apart than a fine cell, and a cell between two beams holds only what a beam
    beside it saw past the top of a low object (scene of 60 LiDAR stations: true poses
    read up to 0.043 of free-space violation with single cells)."""
    view = view_projection(pre)
    if view is None:
        return None
    cell = 1.5 * fine_voxel
    cached = pre._cache.get("depth_grid")
    if cached is None or cached[1] != cell:
        lateral, depth, _, _ = view.project(pre.fine_points, pre.fine_normals)
        keys, reach = cell_keys(lateral, cell), 1.0
        if view.spherical:
            keys, depth = neighbour_keys(keys).ravel(), np.repeat(depth, 27)
            reach = 2.0
        order = np.lexsort((depth, keys))
        keys, depth = keys[order], depth[order]
        last = np.flatnonzero(np.r_[keys[1:] != keys[:-1], True])
        cached = pre._cache["depth_grid"] = (view, cell, keys[last], depth[last], reach)
    return cached


def lateral_tree(pre: PreprocessedScan):
    """(projection, KD-tree of the fine points' lateral coordinates, each point's
    sampling gap); None without a view. A spherical view's feature-level points count
    too, and its ``view_points`` (strays kept): far from a spinning sensor its samples lie
    farther apart than the fine level's stray filter allows, and the directions it
    measured there would read as unseen (60 LiDAR stations: true poses of neighbours read
    0.04-0.10 of unseen points at 11.3-11.5 m of an 11.5 m range; a 200-frame sequence:
    0.042 at 16-22 m, its fine level ending at 22.7 m of a 40.6 m scan). The sampling gap
    of a point is the lateral distance to its third nearest neighbour: how far apart the
    view sampled the surface there. Any other view with a sensor counts its
    ``view_points`` alone (one raw point per fine cell, strays kept): the stray filter
    drops the few samples of thin parts in sparse scans (a chair's legs and rails at
    3k points a scan: 7% of the raw points), and true poses then read up to 0.032 of
    unseen points where the raw scan has a point within 0.6 feature voxels."""
    view = view_projection(pre)
    if view is None:
        return None
    if "lateral_tree" not in pre._cache:
        if pre.view_points is None:
            pts = [pre.fine_points]
        elif view.spherical:
            pts = [pre.fine_points, pre.points, pre.view_points]
        else:
            pts = [pre.view_points]
        lateral, _, _, _ = view.project(np.vstack(pts), np.zeros((sum(map(len, pts)), 3)))
        tree = cKDTree(lateral)
        gap = tree.query(lateral, k=min(4, len(lateral)))[0][:, -1]
        pre._cache["lateral_tree"] = (view, tree, gap)
    return pre._cache["lateral_tree"]


def _violations(grid, points, normals, tolerance, min_cos, min_count) -> float:
    """Share of ``points`` (in the grid scan's frame) in front of its measured surface."""
    view, cell, keys, front, reach = grid
    lateral, depth, cos, ahead = view.project(points, normals)
    facing = (cos >= min_cos) & ahead
    k = cell_keys(lateral[facing], cell)
    pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
    seen = keys[pos] == k
    c = cos[facing]
    slope = np.sqrt(np.clip(1.0 - c**2, 0.0, 1.0)) / np.maximum(c, 1e-3)
    # The width at the point's depth of the cells its front depth may come from.
    span = reach * cell * view.lateral_scale(depth[facing])
    ahead_of = depth[facing] > front[pos] + tolerance + span * slope
    bad = _clustered(points[facing][seen & ahead_of], cell)
    return float(bad / max(np.count_nonzero(seen), min_count))


def _clustered(points: np.ndarray, radius: float, min_points: int = 3) -> int:
    """How many of ``points`` have at least ``min_points`` of them (itself included)
    within ``radius``: a surface put in the wrong place violates in patches, stray
    outlier points one by one. (Not used for the unseen test: a pose turned far off
    leaves only a few facing points, unclustered.)"""
    if len(points) < min_points:
        return 0
    near = cKDTree(points).query_ball_point(points, radius, return_length=True)
    return int(np.count_nonzero(near >= min_points))


def free_space_violation(
    pre_i, pre_j, T_i_j: np.ndarray, cfg: AlignConfig | None = None, *, scales: Scales | None = None
) -> float:
    """Larger of the two scans' shares of points seen through empty space.

    ``pre_i``, ``pre_j``: PreprocessedScans; ``T_i_j`` maps j into i's frame.

    Only points facing the other scan's sensor (cosine >= ``free_space_min_facing_cos``)
    count, and the depth slack is ``free_space_tolerance_voxels * v`` plus the depth a
    cell spans at the point's slope (two cells for a spherical view, whose samples also
    count in the cells around theirs: :func:`depth_grid`); violating points count only in
    clusters (:func:`_clustered`). NaN when either scan has no view direction.
    """
    cfg = cfg or AlignConfig()
    scales = scan_scales(pre_i) if scales is None else scales
    grid_i, grid_j = depth_grid(pre_i, scales.fine_voxel), depth_grid(pre_j, scales.fine_voxel)
    if grid_i is None or grid_j is None:
        return float("nan")
    tol = cfg.free_space_tolerance_voxels * scales.voxel
    args = (tol, cfg.free_space_min_facing_cos, cfg.min_correspondences)
    T_j_i = invert_transform(T_i_j)
    in_i = _violations(
        grid_i, transform_points(T_i_j, pre_j.fine_points), pre_j.fine_normals @ T_i_j[:3, :3].T,
        *args,
    )  # fmt: skip
    in_j = _violations(
        grid_j, transform_points(T_j_i, pre_i.fine_points), pre_i.fine_normals @ T_j_i[:3, :3].T,
        *args,
    )  # fmt: skip
    return max(in_i, in_j)


def _unseen(lateral, points, normals, radius, min_cos, min_count) -> float:
    """Share of facing ``points`` farther across the view from its nearest point than
    ``radius`` (at the point's depth) and than twice that point's sampling gap: a gap of
    the view's own sampling (sparse rings far from a LiDAR) is no hole it saw through."""
    view, tree, gap = lateral
    lat, depth, cos, ahead = view.project(points, normals)
    facing = (cos >= min_cos) & ahead & view.could_see(lat, depth)
    reach = radius / view.lateral_scale(depth[facing])  # the radius at the point's depth
    dist, nn = tree.query(lat[facing], distance_upper_bound=np.max(reach, initial=0.0))
    hole = dist > reach
    near = hole & np.isfinite(dist)  # beyond the reach at its depth, within the largest
    hole[near] = dist[near] > 2.0 * gap[nn[near]]
    far = np.flatnonzero(hole & ~near)
    if len(far):
        d2, n2 = tree.query(lat[facing][far])
        hole[far] = d2 > 2.0 * gap[n2]
    return float(np.count_nonzero(hole) / max(np.count_nonzero(facing), min_count))


def unseen_violation(
    pre_i, pre_j, T_i_j: np.ndarray, cfg: AlignConfig | None = None, *, scales: Scales | None = None
) -> float:
    """Larger of the two scans' shares of points the other view should have seen but did not.

    ``pre_i``, ``pre_j``: PreprocessedScans; ``T_i_j`` maps j into i's frame.

    A point of scan j that faces scan i's sensor (cosine >= ``free_space_min_facing_cos``
    with i's view direction) and is not hidden would have been measured by i, so under a
    correct alignment i has points near it across the view direction (at some depth: in
    front of it if it is hidden). When i has no point within ``unseen_radius_voxels * v``
    across the view direction, i's line of sight there met nothing: the point sits in
    empty space. This catches what :func:`free_space_violation` (points in front of a
    surface i measured) cannot, such as a part put where the other view saw only
    background. It needs no depth, so the orthographic approximation of a perspective
    view matters little. NaN when either scan has no view direction.
    """
    cfg = cfg or AlignConfig()
    scales = scan_scales(pre_i) if scales is None else scales
    lat_i, lat_j = lateral_tree(pre_i), lateral_tree(pre_j)
    if lat_i is None or lat_j is None:
        return float("nan")
    args = (
        cfg.unseen_radius_voxels * scales.voxel,
        cfg.free_space_min_facing_cos,
        cfg.min_correspondences,
    )
    R, t = T_i_j[:3, :3], T_i_j[:3, 3]
    in_i = _unseen(lat_i, pre_j.fine_points @ R.T + t, pre_j.fine_normals @ R.T, *args)
    in_j = _unseen(lat_j, (pre_i.fine_points - t) @ R, pre_i.fine_normals @ R, *args)
    return max(in_i, in_j)


def loosened_view_limits(cfg: AlignConfig) -> tuple[float, float]:
    """The pairwise free-space and unseen limits loosened by ``coarse_gate_slack``: the
    limits for a relative pose that no ICP on that pair has tightened."""
    slack = cfg.coarse_gate_slack
    return (
        min(1.0, cfg.max_free_space_violation * slack),
        min(1.0, cfg.max_unseen_violation * slack),
    )


def seen_from_sensors(*views) -> bool:
    """Whether every view has a sensor position (stored or estimated): the bound on a
    gross conflict holds for views seen from their sensor. Along one axis (no position
    found), a right pose can read far more: chair_model dense seed 1, scan_001 placed at
    its true pose read 0.68 of its points in scan_008's free space, 0.43 in scan_003's."""
    return all(getattr(v, "viewpoint", None) is not None for v in views)


def view_conflicts(fs: float, un: float, shares_surface: bool, cfg: AlignConfig,
                   sensors: bool = True) -> list[str]:  # fmt: skip
    """The one rule for when two placed views contradict each other, given the share of
    one's points in the other's free space (``fs``) and where it saw nothing (``un``):
    ``["gross"]`` when ``fs`` exceeds ``max_free_space_apart`` and both views are seen from
    their sensor (``sensors``), whatever surface they share; otherwise, between views
    that share surface, ``"free_space"`` and/or ``"unseen"`` for each share above its
    loosened pairwise limit (:func:`loosened_view_limits`); ``[]`` for no conflict. NaN
    (no view direction) never contradicts."""
    if fs > cfg.max_free_space_apart and sensors:
        return ["gross"]
    if not shares_surface:
        return []
    fs_limit, un_limit = loosened_view_limits(cfg)
    return [k for k, x, lim in (("free_space", fs, fs_limit), ("unseen", un, un_limit)) if x > lim]


def prepare_scans(pre: Sequence[PreprocessedScan], scales: Scales | None = None) -> None:
    """Build the scans' cached structures that scoring and ICP read (KD-trees on both
    levels, depth grids, lateral trees), so that threads share them afterwards."""
    for p in pre:
        p.fine_tree()
        feature_level_tree(p)
        depth_grid(p, (scan_scales(p) if scales is None else scales).fine_voxel)
        lateral_tree(p)
