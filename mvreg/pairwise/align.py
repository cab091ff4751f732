"""Stage 3: pairwise alignment with an honest quality score.

Per pair (i, j), mapping scan j into scan i's frame (``T_i_j``):

1. *Feature matches*: mutual nearest neighbours of the two scans' FPFH descriptors,
   compared after a PCA to ``feature_dims`` dimensions (fitted on all scans' descriptors
   by :func:`align_pairs`, on the pair's alone by :func:`align_pair`; it keeps >98% of
   their variance) with an approximate KD-tree search (``feature_match_eps``; exact
   search changed no result on the bunny and cost 2.5x).
2. *RANSAC* over triples of matches (vectorised NumPy, seeded ``numpy.random.Generator``):
   a triple must keep its edge lengths (ratio >= ``ransac_edge_length_ratio``) and its
   normals (angle <= ``ransac_normal_angle_deg``); hypotheses are ranked by how many
   matches they explain within ``ransac_distance_voxels * v``, the number of draws
   adapts to the best inlier ratio (``ransac_confidence``), and the best
   ``ransac_validate_top`` *distinct* hypotheses (near-duplicates removed) are re-ranked by
   how much of the whole scan they put onto the other.
   Open3D's ``registration_ransac_based_on_feature_matching`` (``ransac_backend="open3d"``)
   is kept as an alternative: it is slower here and, with more than one thread, not
   reproducible (its threads share one random generator).
3. *Point-to-plane ICP* (NumPy + SciPy KD-trees, deterministic): on the feature level,
   then on the fine level (target: all fine points and their tangent planes; source:
   at most ``icp_max_source_points`` of the fine points) with shrinking distances.
4. *Several hypotheses verified*: on near-symmetric shapes (a body of revolution, a CAD
   part) the first-ranked hypothesis is often a flip or a turn about an axis, and the
   right one lies further down. Up to ``ransac_hypotheses_tried`` of them go through ICP
   and the acceptance rule below: the first one fully; each other one is screened by
   ``screen_icp_iterations`` feature-level ICP iterations and the loosened rule, and
   verified fully only when it passes and ends somewhere new (not within a voxel of a pose
   already tried). Among the accepted ones the pair keeps the one with the most mutual
   correspondences, discounted by its free-space violation (:func:`_support`); the
   teapot's flips pass the rule with 0.003-0.004 of their points in free space, the right
   pose with 0.000 and as many correspondences.

Scores (fine level, after ICP; ``v`` = feature voxel size, ``noise`` = mean of the two
scans' :attr:`~mvreg.pairwise.preprocess.PreprocessedScan.noise`):

* a *neighbour* of a point is the nearest point of the other scan within
  ``score_distance_voxels * v`` whose normal agrees (cosine >= ``score_min_normal_cos``);
  its *residual* is the distance to the neighbour's tangent plane;
* ``fitness``: fraction of scan j's fine points with a neighbour (Open3D's meaning);
* ``residual_ratio``: median residual / noise. A correct alignment leaves residuals like
  the scans' own noise (ratio 1.3-2.5 on the Stanford bunny); a wrong one that ICP pressed
  into contact leaves residuals spread up to the cut-off (ratio > 14 there);
* ``overlap_ratio``: fraction of the better-covered scan whose residual is at most
  ``tight_residual_ratio * noise``: the part that really coincides;
* ``inlier_rmse``: root mean square residual (data units);
* ``num_correspondences``: mutual nearest neighbours with agreeing normals.
* ``free_space_violation``: for scans that look like single views (see
  :func:`~mvreg.pairwise.preprocess.view_direction`), the share of one scan's points that,
  seen from the other scan's sensor direction, lie clearly *in front of* the surface the
  other scan measured there -- where it saw through empty space. Only points facing that
  sensor (cosine >= ``free_space_min_facing_cos``) count, and the depth slack is
  ``free_space_tolerance_voxels * v`` plus the depth a cell spans at the point's slope.
  A correct alignment has almost none (<= 0.001 on the bunny, <= 0.003 on synthetic
  views); a wrong one that fits locally -- the failure mode on smooth or near-symmetric
  shapes, where residuals alone cannot tell -- puts surfaces through each other (>= 0.05
  on the bunny, mostly >= 0.02 on synthetic views, a few near-symmetric teapot poses at
  0.004-0.007). NaN when a scan is not a single view (the test is then skipped).

Acceptance: ``overlap_ratio >= min_overlap_ratio``, ``residual_ratio <= max_residual_ratio``,
``num_correspondences >= min_correspondences`` and (when defined)
``free_space_violation <= max_free_space_violation`` and ``unseen_violation <=
max_unseen_violation`` (:func:`unseen_violation`: points facing the other view's sensor
where it saw nothing at all). How large the residual of a correct
alignment is relative to the within-scan noise depends on the data (about 0.5 for
synthetic i.i.d. noise, 1.3-2.5 for the real bunny scans, whose alignment residual is
dominated by calibration rather than noise), so :func:`align_pairs` also compares pairs
with each other: the reference is the median ``residual_ratio`` of the best-overlapping
quarter of the accepted pairs (at least 3), which are almost always right, and a pair
above ``relative_residual_factor`` times the reference is rejected as well, unless its
median residual is below ``relative_residual_floor_fine_voxels`` fine voxels (noise-free
scans, where the noise estimate sits at its floor).

A pair whose feature-level ICP already fails by a wide margin (thresholds loosened
``coarse_gate_slack`` times) is rejected without fine ICP, which saves most of the time
spent on pairs that do not overlap.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from mvreg.config.align import AlignConfig
from mvreg.executor import Executor, make_executor, single_threaded_blas
from mvreg.geometry import invert_transform, rotation_from_vector, transform_points
from mvreg.pairwise.preprocess import PreprocessedScan


@dataclass
class PairResult:
    """Outcome of aligning scan j to scan i.

    ``T_i_j`` (4, 4) maps scan j's points into scan i's frame. Scores as in the module
    docstring; ``reason`` says why a pair was rejected ("" when accepted).
    """

    i: int
    j: int
    T_i_j: np.ndarray
    overlap_ratio: float
    inlier_rmse: float
    num_correspondences: int
    fitness: float
    accepted: bool
    reason: str
    residual_ratio: float = float("nan")
    free_space_violation: float = float("nan")
    unseen_violation: float = float("nan")
    seconds: float = 0.0
    names: tuple[str, str] = ("", "")
    stats: dict = field(default_factory=dict, repr=False)

    def __repr__(self) -> str:
        state = "accepted" if self.accepted else f"rejected: {self.reason}"
        return (
            f"PairResult({self.i}-{self.j}, overlap={self.overlap_ratio:.2f}, "
            f"residual_ratio={self.residual_ratio:.2f}, rmse={self.inlier_rmse:.3g}, "
            f"corr={self.num_correspondences}, fitness={self.fitness:.2f}, "
            f"free_space_violation={self.free_space_violation:.3f}, {state})"
        )


# ---------------------------------------------------------------------------- geometry


def _kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Batched least-squares rotation+translation: (B, K, 3), (B, K, 3) -> (B, 4, 4)."""
    cs, cd = src.mean(axis=1), dst.mean(axis=1)
    h = np.einsum("bki,bkj->bij", src - cs[:, None], dst - cd[:, None])
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("bji,bkj->bik", vt, u)))
    d[d == 0] = 1.0
    vt = vt * np.stack([np.ones_like(d), np.ones_like(d), d], axis=1)[:, :, None]
    r = np.einsum("bji,bkj->bik", vt, u)
    out = np.tile(np.eye(4), (len(src), 1, 1))
    out[:, :3, :3] = r
    out[:, :3, 3] = cd - np.einsum("bij,bj->bi", r, cs)
    return out


def _triangle_transforms(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(B, 3, 3) source and destination triangles -> (B, 4, 4) rigid maps src -> dst.

    Exact for congruent triangles (frames built from each triangle's edges); much faster
    than a batched SVD and good enough for RANSAC hypotheses, refined later.
    """

    def frames(p: np.ndarray) -> np.ndarray:
        e1 = p[:, 1] - p[:, 0]
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        e3 = np.cross(e1, p[:, 2] - p[:, 0])
        e3 /= np.linalg.norm(e3, axis=1, keepdims=True)
        return np.stack([e1, np.cross(e3, e1), e3], axis=2)  # columns

    with np.errstate(invalid="ignore", divide="ignore"):
        r = frames(dst) @ np.transpose(frames(src), (0, 2, 1))
    out = np.tile(np.eye(4), (len(src), 1, 1))
    out[:, :3, :3] = r
    out[:, :3, 3] = dst.mean(axis=1) - np.einsum("bij,bj->bi", r, src.mean(axis=1))
    return out


def _same_pose(A: np.ndarray, B: np.ndarray, tol: float, centre: np.ndarray, radius: float):
    """Whether two maps of a scan (centroid ``centre``, radius ``radius``) move no point of
    it further than ``tol`` apart (bound: rotation angle x radius + centroid shift)."""
    cos = (np.trace(A[:3, :3] @ B[:3, :3].T) - 1.0) / 2.0
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    shift = (A[:3, :3] - B[:3, :3]) @ centre + A[:3, 3] - B[:3, 3]
    return bool(angle * radius + np.linalg.norm(shift) < tol)


def icp_point_to_plane(
    source: np.ndarray,
    source_normals: np.ndarray,
    target: np.ndarray,
    target_normals: np.ndarray,
    target_tree: cKDTree,
    T_target_source: np.ndarray,
    max_dist: float,
    max_iterations: int = 30,
    min_normal_cos: float = 0.5,
    tolerance: float = 5e-3,
) -> np.ndarray:
    """Point-to-plane ICP (Gauss-Newton on a linearised rotation), deterministic.

    Pairs each source point with its nearest target point within ``max_dist`` whose
    normal agrees (cosine >= ``min_normal_cos``), minimises the squared distances to the
    target tangent planes, and stops when an update moves no point by more than
    ``tolerance * max_dist`` (changing correspondences make it jitter at small scales), or
    when it is back within that of the pose two steps before: two correspondence sets that
    each pull to the other's pose make a 2-cycle, which further steps only repeat.
    Returns the refined (4, 4) ``T_target_source``.
    """
    T = np.array(T_target_source, dtype=np.float64)
    extent = float(np.max(np.linalg.norm(source - source.mean(0), axis=1))) + 1e-300
    centroid = source.mean(0)

    def distance(Ta, Tb):  # how far the two poses put the source points apart (about)
        turn = np.linalg.norm(Ta[:3, :3] - Tb[:3, :3]) / np.sqrt(2.0)
        return turn * extent + np.linalg.norm(
            (Ta[:3, :3] - Tb[:3, :3]) @ centroid + Ta[:3, 3] - Tb[:3, 3]
        )

    before, previous = None, T  # the poses two steps and one step back
    for _ in range(max_iterations):
        q = transform_points(T, source)
        d, nn = target_tree.query(q, distance_upper_bound=max_dist)
        ok = np.flatnonzero(np.isfinite(d))
        if len(ok) < 6:
            break
        n = target_normals[nn[ok]]
        agree = np.einsum("ij,ij->i", n, source_normals[ok] @ T[:3, :3].T) >= min_normal_cos
        ok, n = ok[agree], n[agree]
        if len(ok) < 6:
            break
        p = q[ok]
        r = np.einsum("ij,ij->i", p - target[nn[ok]], n)
        a = np.empty((len(p), 6))
        a[:, 0] = p[:, 1] * n[:, 2] - p[:, 2] * n[:, 1]
        a[:, 1] = p[:, 2] * n[:, 0] - p[:, 0] * n[:, 2]
        a[:, 2] = p[:, 0] * n[:, 1] - p[:, 1] * n[:, 0]
        a[:, 3:] = n
        ata = a.T @ a
        try:
            x = np.linalg.solve(ata + 1e-12 * np.trace(ata) * np.eye(6), -a.T @ r)
        except np.linalg.LinAlgError:
            break
        step = np.eye(4)
        step[:3, :3] = rotation_from_vector(x[:3])
        step[:3, 3] = x[3:]
        before, previous, T = previous, T, step @ T
        if np.linalg.norm(x[:3]) * extent + np.linalg.norm(x[3:]) < tolerance * max_dist:
            break
        if before is not None and distance(T, before) < tolerance * max_dist:
            break
    return T


# ---------------------------------------------------------------------------- RANSAC


@dataclass(frozen=True)
class FeatureBasis:
    """PCA of FPFH descriptors: ``(f - mean) @ basis`` gives the reduced descriptor."""

    mean: np.ndarray
    basis: np.ndarray

    @classmethod
    def fit(cls, feature_sets: Sequence[np.ndarray], dims: int = 16) -> FeatureBasis:
        both = np.vstack(feature_sets)
        mean = both.mean(axis=0)
        _, _, vt = np.linalg.svd(both - mean, full_matrices=False)
        return cls(mean, vt[: min(dims, both.shape[1])].T.copy())


def _reduced_tree(pre: PreprocessedScan, basis: FeatureBasis) -> tuple[np.ndarray, cKDTree]:
    """Reduced descriptors and their KD-tree, cached per basis."""
    cached = pre._cache.get("reduced_features")
    if cached is None or cached[0] is not basis:  # holding the basis keeps `is` meaningful
        reduced = (pre.features - basis.mean) @ basis.basis
        cached = (basis, reduced, cKDTree(reduced))
        pre._cache["reduced_features"] = cached
    return cached[1], cached[2]


def feature_matches(
    pre_i: PreprocessedScan, pre_j: PreprocessedScan, basis: FeatureBasis, eps: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours in (reduced) descriptor space -> (idx_i, idx_j).

    ``eps``: approximate search (``cKDTree.query``), distances within a factor 1 + eps.
    """
    fi, tree_i = _reduced_tree(pre_i, basis)
    fj, tree_j = _reduced_tree(pre_j, basis)
    _, nn_ji = tree_i.query(fj, eps=eps)
    _, nn_ij = tree_j.query(fi, eps=eps)
    idx_j = np.flatnonzero(nn_ij[nn_ji] == np.arange(len(fj)))
    return nn_ji[idx_j].astype(np.int64), idx_j.astype(np.int64)


def _edge_lengths(p: np.ndarray) -> np.ndarray:
    """(B, 3, 3) triangles -> (B, 3) edge lengths."""
    return np.linalg.norm(p - p[:, [1, 2, 0]], axis=2)


def _ransac_numpy(
    pre_i, pre_j, cfg: AlignConfig, seed: int, basis: FeatureBasis | None
) -> tuple[np.ndarray, dict]:
    """Best T_i_j from feature matches; (T, stats). Identity with stats["ok"]=False if none."""
    v = pre_i.voxel_size
    if basis is None:
        basis = FeatureBasis.fit([pre_i.features, pre_j.features], cfg.feature_dims)
    idx_i, idx_j = feature_matches(pre_i, pre_j, basis, cfg.feature_match_eps)
    stats = {"feature_matches": int(len(idx_i)), "ok": False}
    if len(idx_i) < 3:
        return np.eye(4), stats
    dst, src = pre_i.points[idx_i], pre_j.points[idx_j]
    dst_n, src_n = pre_i.normals[idx_i], pre_j.normals[idx_j]
    m = len(idx_i)
    rng = np.random.default_rng(seed)
    dist2 = (cfg.ransac_distance_voxels * v) ** 2
    cos_n = np.cos(np.radians(cfg.ransac_normal_angle_deg))
    log_fail = np.log(1.0 - cfg.ransac_confidence)
    needed, drawn, batch = cfg.ransac_max_iterations, 0, 256
    best_counts = np.zeros(0, np.int64)
    best_T = np.zeros((0, 4, 4))
    pool = 8 * cfg.ransac_validate_top  # near-duplicates are removed at the end
    while drawn < needed:
        draw = rng.integers(0, m, size=(batch, 3))
        drawn += batch
        draw = draw[
            (draw[:, 0] != draw[:, 1]) & (draw[:, 1] != draw[:, 2]) & (draw[:, 0] != draw[:, 2])
        ]
        ls, ld = _edge_lengths(src[draw]), _edge_lengths(dst[draw])
        ok = np.all(
            (np.minimum(ls, ld) >= cfg.ransac_edge_length_ratio * np.maximum(ls, ld)) & (ls > v),
            axis=1,
        )
        draw = draw[ok]
        if len(draw) == 0:
            continue
        hyp = _triangle_transforms(src[draw], dst[draw])
        finite = np.all(np.isfinite(hyp), axis=(1, 2))
        hyp, draw = hyp[finite], draw[finite]
        rot_n = np.einsum("bij,bkj->bki", hyp[:, :3, :3], src_n[draw])
        ok = np.all(np.einsum("bki,bki->bk", rot_n, dst_n[draw]) >= cos_n, axis=1)
        hyp = hyp[ok]
        if len(hyp) == 0:
            continue
        moved = np.einsum("bij,kj->bki", hyp[:, :3, :3], src) + hyp[:, None, :3, 3]
        counts = np.count_nonzero(np.sum((moved - dst) ** 2, axis=2) <= dist2, axis=1)
        best_counts = np.concatenate([best_counts, counts])
        best_T = np.concatenate([best_T, hyp])
        keep = np.argsort(-best_counts, kind="stable")[:pool]
        best_counts, best_T = best_counts[keep], best_T[keep]
        w = best_counts[0] / m
        if w >= 1.0:
            break
        if w > 0:
            needed = min(needed, int(np.ceil(log_fail / np.log1p(-(w**3)))))
    stats["hypotheses_drawn"] = int(drawn)
    if len(best_T) == 0 or best_counts[0] < 3:
        return np.eye(4), stats
    # Distinct hypotheses (a near-symmetric shape has several far apart), each fitted to
    # its inlier matches, re-ranked by the share of scan j they bring onto scan i.
    tree = _feature_level_tree(pre_i)
    kept, fits = [], []
    centre = pre_j.points.mean(axis=0)
    radius = float(np.max(np.linalg.norm(pre_j.points - centre, axis=1)))
    for T in best_T:
        if len(kept) >= cfg.ransac_validate_top:
            break
        if any(_same_pose(T, K, 3 * v, centre, radius) for K in kept):
            continue
        moved = transform_points(T, src)
        inl = np.sum((moved - dst) ** 2, axis=1) <= dist2
        if inl.sum() >= 3:
            T = _kabsch(src[inl][None], dst[inl][None])[0]
        d, _ = tree.query(transform_points(T, pre_j.points), distance_upper_bound=np.sqrt(dist2))
        kept.append(T)
        fits.append(float(np.mean(np.isfinite(d))))
    order = np.argsort(-np.asarray(fits), kind="stable")
    best, best_fit = kept[order[0]], fits[order[0]]
    stats["candidates"] = [kept[k] for k in order]
    stats["candidate_fitness"] = [fits[k] for k in order]
    stats.update(ok=True, ransac_fitness=best_fit, ransac_inlier_ratio=float(best_counts[0] / m))
    return best, stats


def _ransac_open3d(
    pre_i, pre_j, cfg: AlignConfig, seed: int, basis=None
) -> tuple[np.ndarray, dict]:
    import open3d as o3d

    reg = o3d.pipelines.registration
    dist = cfg.ransac_distance_voxels * pre_i.voxel_size
    checkers = [
        reg.CorrespondenceCheckerBasedOnEdgeLength(cfg.ransac_edge_length_ratio),
        reg.CorrespondenceCheckerBasedOnDistance(dist),
        reg.CorrespondenceCheckerBasedOnNormal(np.radians(cfg.ransac_normal_angle_deg)),
    ]
    # Its threads share one random generator: reproducible only on one thread.
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        o3d.utility.random.seed(int(seed))
        result = reg.registration_ransac_based_on_feature_matching(
            pre_j.o3d_cloud(),
            pre_i.o3d_cloud(),
            pre_j.o3d_features(),
            pre_i.o3d_features(),
            True,
            dist,
            reg.TransformationEstimationPointToPoint(False),
            3,
            checkers,
            reg.RANSACConvergenceCriteria(cfg.ransac_max_iterations, cfg.ransac_confidence),
        )
    finally:
        o3d.utility.set_max_threads(threads)
    ok = result.fitness > 0 and len(result.correspondence_set) >= 3
    stats = {"ok": bool(ok), "ransac_fitness": float(result.fitness)}
    return np.asarray(result.transformation).copy(), stats


# ---------------------------------------------------------------------------- scores


def _feature_level_tree(pre: PreprocessedScan) -> cKDTree:
    if "tree" not in pre._cache:
        pre._cache["tree"] = cKDTree(pre.points)
    return pre._cache["tree"]


def nearest_with_normals(tree, pts_dst, nrm_dst, pts_src, nrm_src, T_dst_src, max_dist, cos):
    """Per source point: nearest destination index (-1 if none within max_dist or if the
    normals disagree) and the residual to that point's tangent plane (inf if none)."""
    q = transform_points(T_dst_src, pts_src)
    d, nn = tree.query(q, distance_upper_bound=max_dist)
    found = np.flatnonzero(np.isfinite(d))
    nearest = np.full(len(pts_src), -1, np.int64)
    resid = np.full(len(pts_src), np.inf)
    k = nn[found]
    n_src = nrm_src[found] @ T_dst_src[:3, :3].T
    agree = np.einsum("ij,ij->i", nrm_dst[k], n_src) >= cos
    found, k = found[agree], k[agree]
    nearest[found] = k
    resid[found] = np.abs(np.einsum("ij,ij->i", nrm_dst[k], q[found] - pts_dst[k]))
    return nearest, resid


def _depth_grid(pre: PreprocessedScan):
    """Front-most depth of the fine points per cell of a grid across the view direction."""
    if pre.view_direction is None:
        return None
    if "depth_grid" not in pre._cache:
        d = np.asarray(pre.view_direction, dtype=np.float64)
        a = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(d, a)
        cell = 1.5 * pre.fine_voxel_size
        keys = _cell_keys(pre.fine_points, a, b, cell)
        depth = pre.fine_points @ d
        order = np.lexsort((depth, keys))
        keys, depth = keys[order], depth[order]
        last = np.flatnonzero(np.r_[keys[1:] != keys[:-1], True])
        pre._cache["depth_grid"] = (a, b, d, cell, keys[last], depth[last])
    return pre._cache["depth_grid"]


def _cell_keys(points: np.ndarray, a: np.ndarray, b: np.ndarray, cell: float) -> np.ndarray:
    u = np.floor(points @ a / cell).astype(np.int64)
    w = np.floor(points @ b / cell).astype(np.int64)
    return (u << 32) + w  # exact for |u|, |w| < 2**31 cells


def _violations(grid, points, normals, tolerance, min_cos, min_count) -> float:
    """Share of ``points`` (in the grid scan's frame) in front of its measured surface."""
    a, b, d, cell, keys, front = grid
    cos = normals @ d
    facing = cos >= min_cos
    p = points[facing]
    k = _cell_keys(p, a, b, cell)
    pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
    seen = keys[pos] == k
    slope = np.sqrt(np.clip(1.0 - cos[facing] ** 2, 0.0, 1.0)) / np.maximum(cos[facing], 1e-3)
    ahead = p @ d > front[pos] + tolerance + cell * slope
    bad = _clustered(p[seen & ahead], cell)
    return float(bad / max(np.count_nonzero(seen), min_count))


def _clustered(points: np.ndarray, radius: float, min_points: int = 3) -> int:
    """How many of ``points`` have at least ``min_points`` of them (itself included)
    within ``radius``: a surface put in the wrong place violates in patches, stray
    outlier points one by one (fandisk, 10% outliers: a right pair at 0.008 of its points
    in free space, 0.92 overlap, all of them strays). Not used for the unseen test: a
    pose turned far off leaves only a few facing points, and those few, unclustered, were
    what rejected a 105-degree turn of fandisk (seed 4, outliers)."""
    if len(points) < min_points:
        return 0
    near = cKDTree(points).query_ball_point(points, radius, return_length=True)
    return int(np.count_nonzero(near >= min_points))


def free_space_violation(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    T_i_j: np.ndarray,
    cfg: AlignConfig | None = None,
) -> float:
    """Larger of the two scans' shares of points seen through empty space (module doc).

    NaN when either scan has no view direction.
    """
    cfg = cfg or AlignConfig()
    grid_i, grid_j = _depth_grid(pre_i), _depth_grid(pre_j)
    if grid_i is None or grid_j is None:
        return float("nan")
    tol = cfg.free_space_tolerance_voxels * pre_i.voxel_size
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


def _lateral_tree(pre: PreprocessedScan):
    """The fine points projected across the view direction, and a KD-tree of them."""
    if pre.view_direction is None:
        return None
    if "lateral_tree" not in pre._cache:
        a, b, d = _depth_grid(pre)[:3]
        F = np.stack([a, b])
        pre._cache["lateral_tree"] = (F, d, cKDTree(pre.fine_points @ F.T))
    return pre._cache["lateral_tree"]


def _unseen(lateral, points, normals, radius, min_cos, min_count) -> float:
    F, d, tree = lateral
    facing = normals @ d >= min_cos
    dist, _ = tree.query(points[facing] @ F.T, distance_upper_bound=radius)
    return float(np.count_nonzero(np.isinf(dist)) / max(np.count_nonzero(facing), min_count))


def unseen_violation(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    T_i_j: np.ndarray,
    cfg: AlignConfig | None = None,
) -> float:
    """Larger of the two scans' shares of points the other view should have seen but did not.

    A point of scan j that faces scan i's sensor (cosine >= ``free_space_min_facing_cos``
    with i's view direction) and is not hidden would have been measured by i, so under a
    correct alignment i has points near it across the view direction (at some depth: in
    front of it if it is hidden). When i has no point within ``unseen_radius_voxels * v``
    across the view direction, i's line of sight there met nothing: the point sits in
    empty space. This catches what :func:`free_space_violation` (points in front of a
    surface i measured) cannot: a flipped teapot puts its handle where the other view saw
    only background (0.016-0.15 of the facing points, against 0.000-0.002 for the right
    poses of the synthetic teapot and fandisk at 0.2% noise, with or without outliers;
    0.000 on the real bunny). Unlike the depth test it needs no depth,
    so the orthographic approximation of a perspective view matters little. NaN when either
    scan has no view direction.
    """
    cfg = cfg or AlignConfig()
    lat_i, lat_j = _lateral_tree(pre_i), _lateral_tree(pre_j)
    if lat_i is None or lat_j is None:
        return float("nan")
    args = (
        cfg.unseen_radius_voxels * pre_i.voxel_size,
        cfg.free_space_min_facing_cos,
        cfg.min_correspondences,
    )
    R, t = T_i_j[:3, :3], T_i_j[:3, 3]
    in_i = _unseen(lat_i, pre_j.fine_points @ R.T + t, pre_j.fine_normals @ R.T, *args)
    in_j = _unseen(lat_j, (pre_i.fine_points - t) @ R, pre_i.fine_normals @ R, *args)
    return max(in_i, in_j)


def score_alignment(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    T_i_j: np.ndarray,
    cfg: AlignConfig | None = None,
    level: Literal["fine", "feature"] = "fine",
) -> dict:
    """Quality scores of ``T_i_j`` (see the module docstring) on the fine or feature level.

    Returns a dict: fitness, overlap_ratio, residual_ratio, median_residual, inlier_rmse,
    num_correspondences, free_space_violation and unseen_violation (always on the fine
    level).
    """
    cfg = cfg or AlignConfig()
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
        ti, tj = _feature_level_tree(pre_i), _feature_level_tree(pre_j)
    max_dist, cos = cfg.score_distance_voxels * pre_i.voxel_size, cfg.score_min_normal_cos
    near_j, r_j = nearest_with_normals(ti, pi, ni, pj, nj, T_i_j, max_dist, cos)
    near_i, r_i = nearest_with_normals(tj, pj, nj, pi, ni, invert_transform(T_i_j), max_dist, cos)
    has_j, has_i = near_j >= 0, near_i >= 0
    mutual = np.count_nonzero(near_i[near_j[has_j]] == np.flatnonzero(has_j))
    noise = 0.5 * (pre_i.noise + pre_j.noise)
    res = np.concatenate([r_i[has_i], r_j[has_j]])
    tight = cfg.tight_residual_ratio * noise
    median = float(np.median(res)) if len(res) else float("inf")
    return {
        "fitness": float(np.mean(has_j)),
        "overlap_ratio": max(float(np.mean(r_i <= tight)), float(np.mean(r_j <= tight))),
        "residual_ratio": median / noise,
        "median_residual": median,
        "inlier_rmse": float(np.sqrt(np.mean(res**2))) if len(res) else float("inf"),
        "num_correspondences": int(mutual),
        "free_space_violation": free_space_violation(pre_i, pre_j, T_i_j, cfg),
        "unseen_violation": unseen_violation(pre_i, pre_j, T_i_j, cfg),
    }


def _decide(scores: dict, cfg: AlignConfig, slack: float = 1.0) -> str:
    """'' when the scores pass the acceptance rule (thresholds loosened by ``slack``)."""
    limit = cfg.max_residual_ratio * slack
    if not scores["residual_ratio"] <= limit:
        return f"residual {scores['residual_ratio']:.1f}x the scan noise (limit {limit:.1f})"
    if scores["overlap_ratio"] < cfg.min_overlap_ratio / slack:
        return f"overlap {scores['overlap_ratio']:.2f} below {cfg.min_overlap_ratio / slack:.2f}"
    if scores["num_correspondences"] < cfg.min_correspondences / slack:
        return f"only {scores['num_correspondences']} correspondences"
    limit = min(1.0, cfg.max_free_space_violation * slack)
    if scores["free_space_violation"] > limit:  # NaN (no view direction) passes
        return (
            f"{scores['free_space_violation']:.3f} of the points lie in the other scan's "
            f"free space (limit {limit:.3f})"
        )
    limit = min(1.0, cfg.max_unseen_violation * slack)
    if scores["unseen_violation"] > limit:  # NaN passes
        return (
            f"{scores['unseen_violation']:.3f} of the points lie where the other scan saw "
            f"nothing (limit {limit:.3f})"
        )
    return ""


# ---------------------------------------------------------------------------- pairs


def align_pair(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    cfg: AlignConfig | None = None,
    seed: int = 0,
    *,
    i: int = 0,
    j: int = 1,
    feature_basis: FeatureBasis | None = None,
) -> PairResult:
    """Align scan j to scan i (feature RANSAC, then ICP) and score the result.

    Deterministic for a given ``seed``. ``i`` and ``j`` only label the result.
    ``feature_basis``: PCA of the descriptors shared by a run (fitted on the pair if None).
    """
    cfg = cfg or AlignConfig()
    start = time.perf_counter()
    ransac = _ransac_open3d if cfg.ransac_backend == "open3d" else _ransac_numpy
    with single_threaded_blas():
        return _align_pair(pre_i, pre_j, cfg, seed, i, j, feature_basis, ransac, start)


def _verify(pre_i, pre_j, T, cfg) -> tuple[np.ndarray, str, dict, dict]:
    """ICP from one hypothesis and the acceptance rule: (T, reason, scores, coarse scores).

    Feature-level ICP and scores first; fine ICP and scores only when the loosened rule
    passes there.
    """
    v = pre_i.voxel_size
    T = icp_point_to_plane(
        pre_j.points, pre_j.normals, pre_i.points, pre_i.normals, _feature_level_tree(pre_i),
        T, cfg.icp_coarse_distance_voxels * v, cfg.icp_max_iterations, cfg.icp_min_normal_cos,
    )  # fmt: skip
    coarse = score_alignment(pre_i, pre_j, T, cfg, level="feature")
    reason = _decide(coarse, cfg, slack=cfg.coarse_gate_slack)
    if reason:
        return T, reason, coarse, coarse
    stride = max(1, int(np.ceil(len(pre_j.fine_points) / cfg.icp_max_source_points)))
    src, src_n = pre_j.fine_points[::stride], pre_j.fine_normals[::stride]
    for dist in cfg.icp_fine_distance_voxels:
        T = icp_point_to_plane(
            src, src_n, pre_i.fine_points, pre_i.fine_normals, pre_i.fine_tree(),
            T, dist * v, cfg.icp_max_iterations, cfg.icp_min_normal_cos,
        )  # fmt: skip
    scores = score_alignment(pre_i, pre_j, T, cfg)
    return T, _decide(scores, cfg), scores, coarse


def _discount(share: float, limit: float) -> float:
    """1 - share / limit, at least 0; 1 when the share is undefined (NaN)."""
    return 1.0 if not np.isfinite(share) else max(0.0, 1.0 - share / limit)


def _support(scores: dict, cfg: AlignConfig) -> float:
    """Rank of an accepted hypothesis: mutual correspondences, discounted by its share of
    points in the other view's free space (NaN: no discount)."""
    fs = scores["free_space_violation"]
    return scores["num_correspondences"] * _discount(fs, cfg.max_free_space_violation)


def geometric_support(scores: dict, cfg: AlignConfig) -> float:
    """How well two scans' points support a pose: mutual correspondences, discounted by
    the share of points in the other view's free space and where it saw nothing (each
    relative to its limit; NaN: no discount); 0 when the pose fails the acceptance rule."""
    if _decide(scores, cfg):
        return 0.0
    out = float(scores["num_correspondences"])
    for key, limit in (
        ("free_space_violation", cfg.max_free_space_violation),
        ("unseen_violation", cfg.max_unseen_violation),
    ):
        if limit > 0:
            out *= _discount(scores[key], limit)
    return out


def _align_pair(pre_i, pre_j, cfg, seed, i, j, feature_basis, ransac, start) -> PairResult:
    T, stats = ransac(pre_i, pre_j, cfg, seed, feature_basis)
    stats["seconds_ransac"] = time.perf_counter() - start
    candidates = stats.pop("candidates", [T])[: cfg.ransac_hypotheses_tried]
    reason, scores = "", None
    if not stats["ok"]:
        reason = "feature matching found no consistent alignment"
    else:
        # Every distinct hypothesis is verified: on near-symmetric shapes a wrong one (a
        # flip, a turn about an axis) can rank first and pass the rule as well.
        # Alternatives are screened first (a few feature-level ICP iterations, then the
        # loosened rule) and verified fully only if they pass and lead somewhere new.
        tried = [_verify(pre_i, pre_j, candidates[0], cfg)]
        v = pre_i.voxel_size
        centre = pre_j.points.mean(axis=0)
        radius = float(np.max(np.linalg.norm(pre_j.points - centre, axis=1)))
        seen = [tried[0][0]]
        for T0 in candidates[1:]:
            T0 = icp_point_to_plane(
                pre_j.points, pre_j.normals, pre_i.points, pre_i.normals,
                _feature_level_tree(pre_i), T0, cfg.icp_coarse_distance_voxels * v,
                cfg.screen_icp_iterations, cfg.icp_min_normal_cos,
            )  # fmt: skip
            if any(_same_pose(T0, K, v, centre, radius) for K in seen):
                continue
            seen.append(T0)
            screen = score_alignment(pre_i, pre_j, T0, cfg, level="feature")
            if not _decide(screen, cfg, slack=cfg.coarse_gate_slack):
                tried.append(_verify(pre_i, pre_j, T0, cfg))
                seen.append(tried[-1][0])
        passed = [t for t in tried if not t[1]]
        stats["hypotheses_tried"] = len(tried)
        stats["hypotheses_accepted"] = len(passed)
        T, reason, scores, coarse = max(passed, key=lambda t: _support(t[2], cfg), default=tried[0])
        stats["coarse"] = coarse
    stats["seconds_icp"] = time.perf_counter() - start - stats["seconds_ransac"]
    return pair_result(pre_i, pre_j, i, j, T, reason, scores, stats, start)


def pair_result(pre_i, pre_j, i, j, T, reason: str, scores: dict | None, stats, start):
    """The PairResult of a decided pair (``scores`` None: nothing was found to score)."""
    if scores is None:
        scores = {"fitness": 0.0, "overlap_ratio": 0.0, "inlier_rmse": float("inf")}
        scores |= {"residual_ratio": float("inf"), "num_correspondences": 0}
        scores |= {"free_space_violation": float("nan"), "unseen_violation": float("nan")}
    median = scores.get("median_residual", float("inf"))
    stats["median_residual_fine_voxels"] = median / pre_i.fine_voxel_size
    return PairResult(
        i=i,
        j=j,
        T_i_j=T,
        overlap_ratio=scores["overlap_ratio"],
        inlier_rmse=scores["inlier_rmse"],
        num_correspondences=scores["num_correspondences"],
        fitness=scores["fitness"],
        accepted=not reason,
        reason=reason,
        residual_ratio=scores["residual_ratio"],
        free_space_violation=scores["free_space_violation"],
        unseen_violation=scores["unseen_violation"],
        seconds=time.perf_counter() - start,
        names=(pre_i.name, pre_j.name),
        stats=stats,
    )


def pair_seed(seed: int, i: int, j: int) -> int:
    """Seed of pair (i, j): independent of the order in which pairs are run."""
    return int(np.random.SeedSequence([int(seed), int(i), int(j)]).generate_state(1)[0] >> 1)


def align_pairs(
    pre: Sequence[PreprocessedScan],
    pairs: Sequence[tuple[int, int]],
    cfg: AlignConfig | None = None,
    seed: int = 0,
    progress: Callable[[PairResult], None] | None = None,
    executor: Executor | int = 2,
) -> list[PairResult]:
    """Align every candidate pair; results in the order of ``pairs``.

    Pairs run on ``workers`` threads (KD-tree searches and NumPy release the
    GIL); each pair has its own seed (:func:`pair_seed`), so results do not depend on
    the number of workers or the order of completion. ``progress`` is called (from the
    calling thread) after each pair. The Open3D backend always runs sequentially.
    """
    cfg = cfg or AlignConfig()
    basis = FeatureBasis.fit([p.features for p in pre], cfg.feature_dims)
    for p in pre:  # build the shared KD-trees before the threads start
        p.fine_tree()
        _feature_level_tree(p)
        _reduced_tree(p, basis)
        _depth_grid(p)
        _lateral_tree(p)

    def run(pair: tuple[int, int]) -> PairResult:
        i, j = pair
        return align_pair(pre[i], pre[j], cfg, pair_seed(seed, i, j), i=i, j=j, feature_basis=basis)

    # Open3D's RANSAC is reproducible on one thread only.
    executor = make_executor(1 if cfg.ransac_backend == "open3d" else executor)
    results = executor.map(run, pairs, progress)
    reject_relative_outliers(results, cfg)
    return results


def reject_relative_outliers(results: Sequence[PairResult], cfg: AlignConfig | None = None):
    """Reject accepted pairs whose residual_ratio is far above that of the best pairs.

    Reference: median residual_ratio of the best-overlapping quarter (at least 3) of the
    accepted pairs. Pairs above ``cfg.relative_residual_factor`` times it are marked
    rejected, in place. Returns the reference (None when there are fewer than 3 pairs).
    """
    cfg = cfg or AlignConfig()
    accepted = [r for r in results if r.accepted]
    if cfg.relative_residual_factor is None or len(accepted) < 3:
        return None
    accepted.sort(key=lambda r: -r.overlap_ratio)
    best = accepted[: max(3, len(accepted) // 4)]
    reference = float(np.median([r.residual_ratio for r in best]))
    limit = cfg.relative_residual_factor * reference
    floor = cfg.relative_residual_floor_fine_voxels
    for r in results:
        r.stats["residual_reference"] = reference
        tiny = r.stats.get("median_residual_fine_voxels", float("inf")) <= floor
        if r.accepted and r.residual_ratio > limit and not tiny:
            r.accepted = False
            r.reason = (
                f"residual {r.residual_ratio:.2f}x the scan noise, above "
                f"{cfg.relative_residual_factor:g}x that of the best-overlapping pairs "
                f"({reference:.2f})"
            )
    return reference
