"""Search one scan, or a group of scans moved as one, against the model of the other
registered scans for a second pose that fits: if a distant pose fits as well, the data do
not fix the pose (a discrete symmetry: a knot turned 120 deg onto itself, a box turned
90 deg, a teapot view turned about its axis); if it fits better, the pose is wrong.

The continuous freedoms (a slide along a cylinder, a turn about a sphere's centre) are
found by :func:`mvreg.globalstage.probes.degenerate_direction`; this module finds the
discrete ones, which no local probe reaches. Groups matter because scans that agree with
each other can be wrong together (three teapot views flipped 180 deg as one, linked to the
rest by one pair): no single scan of the group has a better pose, the group has.

Contract (pure functions on preprocessed scans and poses; no I/O):

* :func:`feature_model` gathers the feature level of some scans in the world frame:
  points, normals and FPFH descriptors (rotation invariant, so each scan's own descriptors
  carry over unchanged).
* :func:`motion_candidates` draws world motions of a source model onto a target model by
  RANSAC over mutual descriptor matches (:func:`mvreg.pairwise.hypotheses.ransac_numpy`),
  leaving out the matches the current placement already explains (sequential RANSAC: the
  pose already found would otherwise fill every slot).
* :func:`distant_alternative` refines, by point-to-plane ICP on the fine level, the
  candidates that move the source far (median point motion above ``far_voxels`` feature
  voxels): the ``max_refined`` of :func:`motion_candidates` (``rounds`` rounds) that
  bring the most of it onto the model (at least half as much as the current placement),
  and the pose hypotheses of the source's own pairs with the others (:func:`pair_poses`);
  it returns the first that fits the model as well as the current placement
  (:func:`fits_as_well`) or better and that no other scan's view contradicts more than
  the current placement (:func:`view_conflict`: both free-space tests), or None.

Every threshold is the pairwise acceptance rule's (``AlignConfig``) or in feature voxels;
none is fitted to an object.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mvreg.config.align import AlignConfig
from mvreg.executor import single_threaded_blas
from mvreg.geometry import invert_transform, transform_points
from mvreg.globalstage.scan_model import ScanModel, model_fit, normal_matrix, overlap_spread
from mvreg.pairwise.features import FeatureBasis
from mvreg.pairwise.hypotheses import distinct_poses, ransac_numpy, scan_extent
from mvreg.pairwise.icp import feature_level_tree, icp_point_to_plane
from mvreg.pairwise.scoring import free_space_violation, loosened_view_limits, unseen_violation

# RANSAC motions refined per group of scans moved as one (single scans: 4, the default of
# :func:`distant_alternative`). Groups are few (the sides of bridges), and a group's true
# place can rank far down: teapot sparse seed 1, two views against two others, the turns
# about the body's axis bring 0.80-0.84 of them onto the others, the true place 0.58
# (11th of 14).
GROUP_CANDIDATES = 16


@dataclass
class FeatureModel:
    """The feature level of several scans in the world frame (what RANSAC reads)."""

    name: str
    points: np.ndarray
    normals: np.ndarray
    features: np.ndarray
    _cache: dict = field(default_factory=dict, repr=False)


@dataclass(frozen=True)
class Alternative:
    """A world motion of the source, far from the identity, that fits the model as well
    as the current placement or better."""

    motion: np.ndarray  # (4, 4) world -> world
    angle_deg: float  # its rotation
    overlap: float
    residual_ratio: float
    better: bool  # fits clearly better than the current placement
    base: tuple[float, float]  # (overlap, residual ratio) of the current placement

    def describe(self) -> str:
        how = "better" if self.better else "as well"
        return (
            f"a second pose {self.angle_deg:.0f} deg away fits the other scans {how} "
            f"(overlap {self.overlap:.2f} vs {self.base[0]:.2f}, residual "
            f"{self.residual_ratio:.1f}x vs {self.base[1]:.1f}x the noise)"
        )


def feature_model(pre, T_world_scan: dict[int, np.ndarray], members) -> FeatureModel:
    pts, nrm, feats = [], [], []
    for k in members:
        T = T_world_scan[k]
        pts.append(transform_points(T, pre[k].points))
        nrm.append(pre[k].normals @ T[:3, :3].T)
        feats.append(pre[k].features)
    return FeatureModel("model", np.concatenate(pts), np.concatenate(nrm), np.concatenate(feats))


def motion_candidates(
    target: FeatureModel, source: FeatureModel, acfg: AlignConfig, voxel: float, seed: int,
    far: float, max_matches: int = 1500, rounds: int = 1, guided: bool = False,
) -> list[np.ndarray]:  # fmt: skip
    """Distinct RANSAC world motions of ``source`` onto ``target``, best first, drawn only
    from the descriptor matches that the current placement (the identity) leaves more
    than ``far`` apart; with ``rounds`` > 1, each further round also leaves out the matches
    the motions found so far explain (a near-symmetric shape has a family of poses that
    would otherwise fill every slot). ``guided``: RANSAC also draws among pairwise-consistent
    matches (:mod:`mvreg.pairwise.guided`)."""
    found: list[np.ndarray] = [np.eye(4)]

    def keep(src, dst):  # matches no motion found so far explains, at most max_matches
        mask = np.ones(len(src), bool)
        for M in found:
            mask &= np.linalg.norm(transform_points(M, src) - dst, axis=1) > far
        idx = np.flatnonzero(mask)
        if len(idx) > max_matches:  # an even spread over them: RANSAC's cost grows with it
            mask[:] = False
            mask[idx[np.linspace(0, len(idx) - 1, max_matches).astype(np.int64)]] = True
        return mask

    # The descriptors' PCA from an even sample of both (the full SVD costs more than RANSAC).
    stride = max(1, (len(target.features) + len(source.features)) // 4000)
    basis = FeatureBasis.fit(
        [target.features[::stride], source.features[::stride]], acfg.feature_dims
    )
    out: list[np.ndarray] = []
    for r in range(rounds):
        _, stats = ransac_numpy(target, source, acfg, seed + r, basis, voxel, keep, guided=guided)
        new = list(stats.get("candidates", []))
        if not new:
            break
        out += new
        found += new
    return out


def share_on(target: FeatureModel, source: FeatureModel, M, acfg: AlignConfig, voxel) -> float:
    tree = feature_level_tree(target)
    limit = acfg.ransac_distance_voxels * voxel
    d, _ = tree.query(transform_points(M, source.points), distance_upper_bound=limit)
    return float(np.mean(np.isfinite(d)))


def _moved(M: np.ndarray, pts: np.ndarray) -> float:
    return float(np.median(np.linalg.norm(transform_points(M, pts) - pts, axis=1)))


def refine_on_model(M, src, src_n, model: ScanModel, voxel: float, acfg: AlignConfig,
                    stages=("reach", "fine")):  # fmt: skip
    """Point-to-plane ICP of the world points ``src`` moved by ``M`` on ``model``: from the
    RANSAC inlier distance plus a voxel (stage "reach": 20 iterations, or its first 5,
    "early", and the other 15, "rest"), then within one voxel ("fine"). Returns the
    refined M."""
    reach = (acfg.ransac_distance_voxels + 1.0) * voxel
    plan = {"early": (reach, 5), "rest": (reach, 15), "reach": (reach, 20), "fine": (voxel, 10)}
    for dist, iters in (plan[k] for k in stages):
        M = icp_point_to_plane(
            src, src_n, model.points, model.normals, model.tree, M, dist, iters,
            acfg.icp_min_normal_cos,
        )  # fmt: skip
    return M


def view_conflict(group, pre, T_world_scan, others, M: np.ndarray, acfg: AlignConfig, cache=None):
    """The first (scan of ``others``, description) whose view contradicts the ``group``
    moved by the world motion ``M`` more than it contradicts the current placement (share
    of points in its free space, or where it saw nothing, higher by more than the pairwise
    limit loosened by ``coarse_gate_slack``); None when no view tells the two apart.
    ``cache``: a dict kept across calls with the same placement (the current placement's
    shares are computed once in it).
    Differences, not raw shares: between right poses of views that share no surface both
    tests read above their limits (docs/design/verification.md)."""
    cache = {} if cache is None else cache
    fs_limit, un_limit = loosened_view_limits(acfg)
    for k in others:
        T_k_world = invert_transform(T_world_scan[k])
        for s in group:
            alt, cur = T_k_world @ M @ T_world_scan[s], T_k_world @ T_world_scan[s]
            for test, limit, what in (
                (free_space_violation, fs_limit, "free space"),
                (unseen_violation, un_limit, "unseen space"),
            ):
                key = (k, s, what)
                if key not in cache:
                    cache[key] = test(pre[k], pre[s], cur, acfg)
                extra = test(pre[k], pre[s], alt, acfg) - cache[key]
                if extra > limit:  # NaN (no view direction) never contradicts
                    return k, f"{extra:.3f} more of the points in {pre[k].name}'s {what}"
    return None


def pair_poses(s, results, T_placed, accepted: bool = False) -> list[np.ndarray]:
    """World poses of scan ``s`` from the pose hypotheses of its pairs with scans of
    ``T_placed`` (``PairResult``, accepted or not: ``T_i_j`` and
    ``stats["pose_hypotheses"]``; with ``accepted``, also every hypothesis the pair's
    aligner accepted, ``stats["accepted_hypotheses"]``), each carried into the world by
    the partner's pose."""
    out = []
    for r in results:
        if s not in (r.i, r.j) or (r.j if r.i == s else r.i) not in T_placed:
            continue
        more = [T for T, _ in r.stats.get("accepted_hypotheses", [])] if accepted else []
        for T_i_j in [r.T_i_j, *r.stats.get("pose_hypotheses", []), *more]:
            if r.i == s:  # p_s = T_i_j p_j
                out.append(T_placed[r.j] @ invert_transform(T_i_j))
            else:
                out.append(T_placed[r.i] @ T_i_j)
    return out


def fits_as_well(overlap, ratio, base_overlap, base_ratio, n, acfg: AlignConfig) -> bool:
    """Whether a distant pose explains the source as well as the current placement: its
    residual within the acceptance rule and no worse than the current one's beyond the
    sampling spread of a median over ``n`` matched points (relative, 3/sqrt(n)), and
    at least half the current overlap (and the pairwise minimum). Overlap alone does not
    rank two poses: a scan on a near-symmetric shape, placed where its copy is covered,
    overlaps the others more than at its true place, which they may barely cover; the
    rest of it then lies where no scan looked, which the caller checks
    (:func:`view_conflict`)."""
    return (
        ratio <= acfg.max_residual_ratio
        and ratio <= base_ratio * (1.0 + 3.0 / np.sqrt(max(n, 1)))
        and overlap >= max(acfg.min_overlap_ratio, 0.5 * base_overlap)
    )


def fits_better(overlap, ratio, base_overlap, base_ratio, n, acfg: AlignConfig) -> bool:
    """Whether a distant pose that fits as well (:func:`fits_as_well`) fits clearly better
    than the current placement, over ``n`` sampled points: a larger overlap beyond the
    sampling spread (:func:`~mvreg.globalstage.scan_model.overlap_spread`) at no larger
    residual; or the current placement does not fit as well as the distant pose by the
    same rule with the two swapped (its residual beyond the distant pose's sampling
    spread, or under half its overlap). Between two poses each of which fits as well as
    the other, the data cannot choose (``undetermined``); when only one direction holds,
    they can, and the current placement is the one they reject. chair_model sparse seed
    1: scan_003 held 27.6 deg off by two agreeing wrong pairs, its true pose 29 deg away
    at residual 0.9x the noise against 1.2x (overlap 0.88 vs 0.87)."""
    if overlap > base_overlap + overlap_spread(base_overlap, n) and ratio <= base_ratio:
        return True
    return not fits_as_well(base_overlap, base_ratio, overlap, ratio, overlap * n, acfg)


def distant_alternative(
    group,
    pre,
    T_world_scan: dict[int, np.ndarray],
    others,
    model: ScanModel,
    voxel: float,
    acfg: AlignConfig,
    far_voxels: float = 2.0,
    max_source: int = 500,
    max_refined: int = 4,
    rounds: int = 2,
    results=(),
    turns=(),
) -> Alternative | None:
    """A world motion of the scans ``group`` (moved as one), far from the identity, under
    which they fit ``model`` (the fine level of ``others``) as well or better and that no
    view of ``others`` contradicts more; or None (module docstring). Besides RANSAC on the
    model, the pose hypotheses of the group's pairs with ``others`` (``results``,
    :func:`pair_poses`) are tried: a pair sees the place the model barely covers, which
    RANSAC on the whole model ranks below the well-covered symmetric copies. ``turns``:
    world motions to try as well (the turns about the axis of the registered scans, when
    they are close to a body of revolution: :func:`axis_turns`)."""
    with single_threaded_blas():  # small SVDs and solves: threads only busy-wait
        return _search(group, pre, T_world_scan, others, model, voxel, acfg, far_voxels,
                       max_source, max_refined, rounds, results, turns)  # fmt: skip


def _search(group, pre, T_world_scan, others, model, voxel, acfg, far_voxels, max_source,
            max_refined, rounds, results, turns) -> Alternative | None:  # fmt: skip
    group = list(group)
    target = feature_model(pre, T_world_scan, others)
    source = feature_model(pre, T_world_scan, group)
    if len(target.features) < 3 or len(source.features) < 3:
        return None  # no descriptors to match (scans preprocessed without them)
    far = far_voxels * voxel
    candidates = motion_candidates(
        target, source, acfg, voxel, seed=min(group), far=far, rounds=rounds
    )
    placed = {k: T_world_scan[k] for k in others}
    poses = [(s, P) for s in group for P in pair_poses(s, results, placed, accepted=True)]
    from_pairs = [P @ invert_transform(T_world_scan[s]) for s, P in poses]
    if not candidates and not from_pairs and not turns:
        return None
    src = np.concatenate([transform_points(T_world_scan[s], pre[s].fine_points) for s in group])
    src_n = np.concatenate([pre[s].fine_normals @ T_world_scan[s][:3, :3].T for s in group])
    stride = max(1, int(np.ceil(len(src) / max_source)))
    src, src_n = src[::stride], src_n[::stride]
    noise = float(np.median([pre[s].noise for s in group]))

    def fit(M):
        overlap, ratio, *_ = model_fit(
            model, transform_points(M, src), src_n @ M[:3, :3].T, noise, voxel, acfg
        )
        return overlap, ratio

    base = fit(np.eye(4))
    floor = 0.5 * share_on(target, source, np.eye(4), acfg, voxel)

    def best_far(cands, limit=max_refined, floor=floor):  # far ones bringing most onto it
        shares = [share_on(target, source, M, acfg, voxel) for M in cands]
        order = np.argsort(-np.asarray(shares), kind="stable")
        return [
            cands[k] for k in order if shares[k] >= floor and _moved(cands[k], source.points) > far
        ][:limit]

    from_pairs = distinct_poses(from_pairs, far, *scan_extent(source.points))
    tried = best_far(candidates) + best_far(from_pairs, 24, acfg.min_overlap_ratio)
    # Each candidate in three stages (5 and 15 ICP iterations from the RANSAC reach, 10
    # within a voxel); after each of the first two it goes on only when it lands far from
    # the current placement, in a basin no earlier candidate reached, and with at least a
    # quarter, then half, of the overlap :func:`fits_as_well` asks for (later stages only
    # tighten the fit). Same outcomes on 10 sets at a third of the ICP: most candidates
    # drawn from pair hypotheses and RANSAC on a right pose are settled after 5 iterations
    # (the bunny: 98 of 98; 15 builtin scans of 40k points: 105 of 213).
    need = max(acfg.min_overlap_ratio, 0.5 * base[0])
    examined: list[np.ndarray] = []
    views: dict = {}  # the current placement's free-space shares, once

    def refined(M):  # the candidate refined, or None where a stage rules it out
        for stage, floor in (("early", 0.25), ("rest", 0.5), ("fine", None)):
            M = refine_on_model(M, src, src_n, model, voxel, acfg, stages=(stage,))
            if _moved(M, src) <= far:
                return None  # came back to the current placement
            if floor is None:
                return M
            if any(_moved(M @ invert_transform(P), src) <= voxel for P in examined):
                return None  # the basin of a candidate already examined (and not kept)
            if stage == "rest":
                examined.append(M)
            if fit(M)[0] < floor * need:
                return None
        return M

    for M in tried + best_far(list(turns), len(turns), acfg.min_overlap_ratio):
        M = refined(M)
        if M is None:
            continue
        overlap, ratio = fit(M)
        if not fits_as_well(overlap, ratio, base[0], base[1], base[0] * len(src), acfg):
            continue
        if view_conflict(group, pre, T_world_scan, others, M, acfg, views) is not None:
            continue
        better = fits_better(overlap, ratio, base[0], base[1], len(src), acfg)
        angle = float(np.degrees(Rotation.from_matrix(M[:3, :3]).magnitude()))
        return Alternative(M, angle, overlap, ratio, better, base)
    return None


def _self_matches(union: FeatureModel, acfg: AlignConfig, far: float, max_points: int, k=12):
    """Each sampled point of ``union`` matched to its nearest descriptor among the points
    more than ``far`` from it (so not to itself or its own neighbourhood): (idx_i, idx_j)."""
    stride = max(1, len(union.features) // 4000)
    basis = FeatureBasis.fit([union.features[::stride]], acfg.feature_dims)
    reduced = (union.features - basis.mean) @ basis.basis
    src = np.unique(np.linspace(0, len(reduced) - 1, max_points).astype(np.int64))
    _, nn = cKDTree(reduced).query(reduced[src], k=min(k, len(reduced)))
    apart = np.linalg.norm(union.points[nn] - union.points[src][:, None, :], axis=2) > far
    has = apart.any(axis=1)
    first = np.argmax(apart, axis=1)
    return nn[has, first[has]].astype(np.int64), src[has]


def axis_turns(
    points, normals, angles_deg=(60.0, 90.0, 120.0, 180.0), max_ratio: float = 0.1
) -> list[np.ndarray]:
    """World motions turning the surface (``points``, ``normals``) about its axis by
    ``angles_deg`` both ways (180 once), when it is close to a body of revolution: the
    weakest direction of its point-to-plane normal matrix is a turn, at most ``max_ratio``
    as constrained as the next one (a turn about the axis slides the surface along
    itself); else none. The axis passes where that motion is along it, not through the
    centroid, which a partial view moves off the axis."""
    H, c, L = normal_matrix(points, normals)
    lam, vecs = np.linalg.eigh(H)
    e = vecs[:, 0]
    w, t = e[:3], e[3:]
    if not lam[0] <= max_ratio * lam[1] or np.linalg.norm(w) < 0.2 * np.linalg.norm(e):
        return []
    axis = w / np.linalg.norm(w)
    through = c + np.cross(w, t) * L / float(np.dot(w, w))
    out = []
    for a in angles_deg:
        for sign in (1.0,) if a == 180.0 else (1.0, -1.0):
            M = np.eye(4)
            M[:3, :3] = Rotation.from_rotvec(sign * np.radians(a) * axis).as_matrix()
            M[:3, 3] = through - M[:3, :3] @ through
            out.append(M)
    return out


def principal_turns(model: ScanModel, voxel: float, acfg: AlignConfig, max_points: int = 1500):
    """Near-symmetries of the registered scans (``model``, their fine level) to try a scan
    at: the turns of 180 deg about the three principal axes of their points through the
    centroid (the turns that map a box, a plate or a bar onto itself), each refined by ICP
    of the model onto itself, kept when they map at least the pairwise minimum overlap of
    it onto itself within the acceptance rule's residual. A scan of a near-symmetric part
    fits the turned copy of the model as well as its true place, and the copy is often the
    one every search proposes; its true place is then the turn of that proposal."""
    stride = max(1, len(model.points) // max_points)
    src, src_n = model.points[::stride], model.normals[::stride]
    centre = src.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((src - centre).T))
    noise = float(np.median(model.noise))
    out = []
    for k in range(3):
        M = np.eye(4)
        M[:3, :3] = Rotation.from_rotvec(np.pi * axes[:, k]).as_matrix()
        M[:3, 3] = centre - M[:3, :3] @ centre
        M = refine_on_model(M, src, src_n, model, voxel, acfg)
        overlap, ratio, *_ = model_fit(
            model, transform_points(M, src), src_n @ M[:3, :3].T, noise, voxel, acfg
        )
        if overlap >= acfg.min_overlap_ratio and ratio <= acfg.max_residual_ratio:
            out.append(M)
    return out


def self_symmetry(
    pre,
    T_world_scan: dict[int, np.ndarray],
    model: ScanModel,
    voxel: float,
    acfg: AlignConfig,
    far_voxels: float = 3.0,
    max_points: int = 1500,
    max_refined: int = 4,
    min_overlap: float = 0.5,
) -> Alternative | None:
    """A world motion, far from the identity, that maps the registered scans (all of
    ``T_world_scan``; ``model`` their fine level) onto themselves: at least
    ``min_overlap`` of their points land on their surface within the acceptance rule's
    residual, and no view contradicts the moved scans more than the scans in place
    (:func:`view_conflict`). An object with such a symmetry lets each scan take any of
    its symmetric places where the others do not cover the copy; or None."""
    with single_threaded_blas():
        members = sorted(T_world_scan)
        union = feature_model(pre, T_world_scan, members)
        if len(union.features) < 3:
            return None
        far = far_voxels * voxel
        # A symmetry moves points by a good part of the object's size: matches between
        # points closer than a fifth of its rms radius only find the identity's basin.
        q = union.points - union.points.mean(axis=0)
        apart = max(far, 0.2 * float(np.sqrt(np.mean(np.sum(q * q, axis=1)))))
        matches = _self_matches(union, acfg, apart, max_points)
        tried: list[tuple[np.ndarray, bool]] = []  # (motion, refine it)
        if len(matches[0]) >= 3:
            _, stats = ransac_numpy(
                union, union, acfg, 0, None, voxel, matches=matches, guided=False
            )
            found = [M for M in stats.get("candidates", []) if _moved(M, union.points) > far]
            shares = [share_on(union, union, M, acfg, voxel) for M in found]
            tried += [(found[k], True) for k in np.argsort(-np.asarray(shares), kind="stable")]
            tried = tried[:max_refined]
        # Turns about the axis of a near body of revolution (a turned part, low poly) map
        # it onto itself; descriptor matches between facets do not propose them (they find
        # one facet step), and ICP would slide a turn back along the axis: taken as they are.
        tried += [(M, False) for M in axis_turns(union.points, union.normals)]
        stride = max(1, len(model.points) // max_points)
        src, src_n = model.points[::stride], model.normals[::stride]
        noise = float(np.median(model.noise))
        views: dict = {}
        for M, refine in tried:
            M = refine_on_model(M, src, src_n, model, voxel, acfg) if refine else M
            if _moved(M, src) <= far:
                continue
            overlap, ratio, *_ = model_fit(
                model, transform_points(M, src), src_n @ M[:3, :3].T, noise, voxel, acfg
            )
            if overlap < min_overlap or not ratio <= acfg.max_residual_ratio:
                continue
            if view_conflict(members, pre, T_world_scan, members, M, acfg, views) is not None:
                continue
            angle = float(np.degrees(Rotation.from_matrix(M[:3, :3]).magnitude()))
            return Alternative(M, angle, overlap, ratio, False, (1.0, 0.0))
    return None
