"""Pose hypotheses for a pair of scans from feature matches (RANSAC), and pose comparison.

Takes two preprocessed scans, their feature matches (:mod:`mvreg.pairwise.features`),
the ``AlignConfig``, a seed and the run's feature voxel ``voxel``. A RANSAC backend
(:data:`RANSAC_BACKENDS`, chosen by ``AlignConfig.ransac_backend``) returns
``(T_i_j, stats)``: its best (4, 4) hypothesis (identity when none) and a dict with at
least ``ok`` (a hypothesis was found) and ``ransac_fitness``; the NumPy backend also
lists up to ``ransac_validate_top`` *distinct* hypotheses in ``stats["candidates"]``,
best first, for the aligner to verify.

NumPy backend (default): triples of matches drawn with a seeded
``numpy.random.Generator``; a triple must keep its edge lengths (ratio >=
``ransac_edge_length_ratio``) and its normals (angle <= ``ransac_normal_angle_deg``);
hypotheses are ranked by how many matches they explain within
``ransac_distance_voxels * voxel``, the number of draws adapts to the best inlier ratio
(``ransac_confidence``); where the draws reach ``ransac_max_iterations`` short of that
confidence (few right matches among many), as many again are drawn among matches that
agree pairwise (:mod:`mvreg.pairwise.guided`; ``guided``, by default
``ransac_guided``). The best distinct
hypotheses (near-duplicates removed) are refitted
to their inliers and re-ranked by how much of the whole scan j they put onto scan i.
Deterministic for a seed. Open3D backend: Open3D's
``registration_ransac_based_on_feature_matching``, run on one thread (its threads share
one random generator). Measurements behind the choices: ``docs/design/pairwise.md``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mvreg.config.align import AlignConfig
from mvreg.geometry import transform_points
from mvreg.pairwise.features import FeatureBasis, feature_matches
from mvreg.pairwise.guided import compatibility, draw_triples
from mvreg.pairwise.icp import feature_level_tree
from mvreg.pairwise.preprocess import PreprocessedScan

RansacBackend = Callable[..., tuple[np.ndarray, dict]]

# Guided draws (:mod:`.guided`) build their compatibility graph on at most this many matches.
GUIDED_MAX_MATCHES = 1500


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
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


def triangle_transforms(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
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


def edge_lengths(p: np.ndarray) -> np.ndarray:
    """(B, 3, 3) triangles -> (B, 3) edge lengths."""
    return np.linalg.norm(p - p[:, [1, 2, 0]], axis=2)


def scan_extent(points: np.ndarray) -> tuple[np.ndarray, float]:
    """(centroid (3,), radius): the largest distance of a point from the centroid."""
    centre = points.mean(axis=0)
    return centre, float(np.max(np.linalg.norm(points - centre, axis=1)))


def same_pose(A: np.ndarray, B: np.ndarray, tol: float, centre: np.ndarray, radius: float):
    """Whether two maps of a scan (centroid ``centre``, radius ``radius``) move no point of
    it further than ``tol`` apart (bound: rotation angle x radius + centroid shift)."""
    cos = (np.trace(A[:3, :3] @ B[:3, :3].T) - 1.0) / 2.0
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    shift = (A[:3, :3] - B[:3, :3]) @ centre + A[:3, 3] - B[:3, 3]
    return bool(angle * radius + np.linalg.norm(shift) < tol)


def distinct_poses(poses, tol: float, centre: np.ndarray, radius: float) -> list[np.ndarray]:
    """``poses`` in order, leaving out each one within ``tol`` (:func:`same_pose`) of one
    kept before it."""
    if len(poses) < 2:
        return list(poses)
    P = np.asarray(poses, dtype=np.float64)
    R = P[:, :3, :3]
    cos = (np.einsum("kab,lab->kl", R, R) - 1.0) / 2.0
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    at = R @ centre + P[:, :3, 3]  # where each pose puts the centre
    shift = np.linalg.norm(at[:, None] - at[None], axis=2)
    close = angle * radius + shift < tol
    kept: list[int] = []
    for k in range(len(P)):
        if not kept or not close[k, kept].any():
            kept.append(k)
    return [poses[k] for k in kept]


def ransac_numpy(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    cfg: AlignConfig,
    seed: int,
    basis: FeatureBasis | None,
    voxel: float,
    keep_matches: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    matches: tuple[np.ndarray, np.ndarray] | None = None,
    guided: bool | None = None,
) -> tuple[np.ndarray, dict]:
    """Best T_i_j from feature matches; (T, stats). Identity with stats["ok"]=False if none.

    ``keep_matches``: optional filter of the matches, (points of j, points of i) -> bool
    mask (e.g. to drop the matches a known pose explains and look for another one).
    ``matches``: (idx_i, idx_j) to use instead of the mutual descriptor matches.
    ``guided``: when the plain draws stop at ``ransac_max_iterations`` short of the
    confidence, draw as many again among pairwise-consistent matches (:mod:`.guided`);
    None: ``cfg.ransac_guided``.
    """
    guided = cfg.ransac_guided if guided is None else guided
    if matches is not None:
        idx_i, idx_j = matches
    else:
        if basis is None:
            basis = FeatureBasis.fit([pre_i.features, pre_j.features], cfg.feature_dims)
        idx_i, idx_j = feature_matches(pre_i, pre_j, basis, cfg.feature_match_eps)
    if keep_matches is not None:
        mask = keep_matches(pre_j.points[idx_j], pre_i.points[idx_i])
        idx_i, idx_j = idx_i[mask], idx_j[mask]
    stats = {"feature_matches": int(len(idx_i)), "ok": False}
    if len(idx_i) < 3:
        return np.eye(4), stats
    src, dst = pre_j.points[idx_j], pre_i.points[idx_i]
    normals = (pre_j.normals[idx_j], pre_i.normals[idx_i])
    counts, hypotheses, stats["hypotheses_drawn"] = _draw(
        src, dst, normals, cfg, seed, voxel, guided
    )
    if len(hypotheses) == 0 or counts[0] < 3:
        return np.eye(4), stats
    kept, fits = _rerank(hypotheses, src, dst, pre_i, pre_j, cfg, voxel)
    order = np.argsort(-np.asarray(fits), kind="stable")
    best, best_fit = kept[order[0]], fits[order[0]]
    stats["candidates"] = [kept[k] for k in order]
    stats["candidate_fitness"] = [fits[k] for k in order]
    m = len(idx_i)
    stats.update(ok=True, ransac_fitness=best_fit, ransac_inlier_ratio=float(counts[0] / m))
    return best, stats


def _draw(src, dst, normals, cfg: AlignConfig, seed: int, voxel: float, guided: bool = False):
    """Adaptive RANSAC over triples of matches (src[k] -> dst[k]); with ``guided``, as
    many triples again drawn among pairwise-consistent matches (:mod:`.guided`).

    Returns the inlier counts (descending) and (K, 4, 4) hypotheses of the best
    ``8 * ransac_validate_top`` draws, and the number of triples drawn.
    """
    m = len(src)
    pool = _Pool(src, dst, normals, cfg, voxel)
    rng = np.random.default_rng(seed)
    log_fail = np.log(1.0 - cfg.ransac_confidence)
    needed, drawn, batch = cfg.ransac_max_iterations, 0, 256
    while drawn < needed:
        draw = rng.integers(0, m, size=(batch, 3))
        drawn += batch
        draw = draw[
            (draw[:, 0] != draw[:, 1]) & (draw[:, 1] != draw[:, 2]) & (draw[:, 0] != draw[:, 2])
        ]
        w = pool.add(draw)
        if w >= 1.0:
            break
        if w > 0:
            needed = min(needed, int(np.ceil(log_fail / np.log1p(-(w**3)))))
    if guided and drawn >= cfg.ransac_max_iterations and pool.inlier_share() < 1.0:
        # The plain draws stopped at the cap, short of the confidence asked for.
        sub = np.arange(m)
        if m > GUIDED_MAX_MATCHES:  # the compatibility test costs m^2: an even subset
            sub = np.linspace(0, m - 1, GUIDED_MAX_MATCHES).astype(np.int64)
        dist = cfg.ransac_distance_voxels * voxel
        indptr, indices = compatibility(
            src[sub], dst[sub], normals[0][sub], normals[1][sub], dist,
            cfg.ransac_normal_angle_deg, voxel,
        )  # fmt: skip
        g_rng = np.random.default_rng([seed, 1])
        for _ in range(0, cfg.ransac_max_iterations, batch):
            pool.add(sub[draw_triples(g_rng, indptr, indices, batch)])
            drawn += batch
    return pool.counts, pool.T, int(drawn)


class _Pool:
    """The best hypotheses of the triples scored so far (``8 * ransac_validate_top``)."""

    def __init__(self, src, dst, normals, cfg: AlignConfig, voxel: float):
        self.src, self.dst, self.normals, self.cfg, self.voxel = src, dst, normals, cfg, voxel
        self.dist2 = (cfg.ransac_distance_voxels * voxel) ** 2
        self.cos_n = np.cos(np.radians(cfg.ransac_normal_angle_deg))
        self.size = 8 * cfg.ransac_validate_top  # near-duplicates are removed at the end
        self.counts = np.zeros(0, np.int64)
        self.T = np.zeros((0, 4, 4))

    def inlier_share(self) -> float:
        return float(self.counts[0] / len(self.src)) if len(self.counts) else 0.0

    def add(self, draw: np.ndarray) -> float:
        """Score the triples ``draw`` (B, 3); returns the best inlier share so far."""
        src, dst, cfg = self.src, self.dst, self.cfg
        src_n, dst_n = self.normals
        ls, ld = edge_lengths(src[draw]), edge_lengths(dst[draw])
        ok = np.all(
            (np.minimum(ls, ld) >= cfg.ransac_edge_length_ratio * np.maximum(ls, ld))
            & (ls > self.voxel),
            axis=1,
        )
        draw = draw[ok]
        if len(draw) == 0:
            return self.inlier_share()
        hyp = triangle_transforms(src[draw], dst[draw])
        finite = np.all(np.isfinite(hyp), axis=(1, 2))
        hyp, draw = hyp[finite], draw[finite]
        rot_n = np.einsum("bij,bkj->bki", hyp[:, :3, :3], src_n[draw])
        hyp = hyp[np.all(np.einsum("bki,bki->bk", rot_n, dst_n[draw]) >= self.cos_n, axis=1)]
        if len(hyp) == 0:
            return self.inlier_share()
        moved = np.einsum("bij,kj->bki", hyp[:, :3, :3], src) + hyp[:, None, :3, 3]
        counts = np.count_nonzero(np.sum((moved - dst) ** 2, axis=2) <= self.dist2, axis=1)
        counts = np.concatenate([self.counts, counts])
        keep = np.argsort(-counts, kind="stable")[: self.size]
        self.counts, self.T = counts[keep], np.concatenate([self.T, hyp])[keep]
        return self.inlier_share()


def _rerank(hypotheses, src, dst, pre_i, pre_j, cfg: AlignConfig, voxel: float):
    """Distinct hypotheses (a near-symmetric shape has several far apart), each fitted to
    its inlier matches, and the share of scan j each brings onto scan i: (poses, shares)."""
    dist2 = (cfg.ransac_distance_voxels * voxel) ** 2
    tree = feature_level_tree(pre_i)
    kept, fits = [], []
    centre, radius = scan_extent(pre_j.points)
    for T in hypotheses:
        if len(kept) >= cfg.ransac_validate_top:
            break
        if any(same_pose(T, K, 3 * voxel, centre, radius) for K in kept):
            continue
        moved = transform_points(T, src)
        inl = np.sum((moved - dst) ** 2, axis=1) <= dist2
        if inl.sum() >= 3:
            T = kabsch(src[inl][None], dst[inl][None])[0]
        d, _ = tree.query(transform_points(T, pre_j.points), distance_upper_bound=np.sqrt(dist2))
        kept.append(T)
        fits.append(float(np.mean(np.isfinite(d))))
    return kept, fits


def ransac_open3d(pre_i, pre_j, cfg: AlignConfig, seed: int, basis, voxel: float):
    """Open3D's feature RANSAC: like :func:`ransac_numpy` (same arguments and (T, stats)),
    but ``basis`` is unused (it matches the full descriptors) and no candidate list."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    dist = cfg.ransac_distance_voxels * voxel
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


RANSAC_BACKENDS: dict[str, RansacBackend] = {"numpy": ransac_numpy, "open3d": ransac_open3d}
