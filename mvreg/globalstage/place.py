"""Place the scans the pair graph left out (no accepted pair, or dropped by verification)
by searching each against the model of the verified scans, and keep a placement only when
it passes everything a verified scan must.

A pair sees only what two views share; the union of the verified scans covers far more of
the object, so a scan whose every pair was too small or too ambiguous to accept often
finds its place on the union (scan-to-model registration).

Contract (pure function; no I/O): :func:`place_leftovers` takes the preprocessed scans,
the verified poses ``{scan: T_world_scan}`` and the scans to try, and returns
``{scan: (T_world_scan, ScanVerification)}`` of the scans it placed, each with evidence
``"model search"``. A placement is kept when, against the union of the verified scans:

* RANSAC over descriptor matches (:func:`mvreg.globalstage.model_search.motion_candidates`,
  with the draws among pairwise-consistent matches, :mod:`mvreg.pairwise.guided`: on the
  model of many scans few mutual matches are right); where none of those passes, the best
  of them turned by the model's near-symmetries
  (:func:`mvreg.globalstage.model_search.principal_turns`: on a near-symmetric part every
  proposal may fall on the turned copy); then starts that need no descriptors
  (:func:`rotation_candidates`: the icosahedral rotations at anchors spread over the model,
  a few ICP iterations each); and point-to-plane ICP on the fine level (last trimmed to
  the noise band) bring it to a pose whose overlap share and residual pass the pairwise
  acceptance rule (overlap at least :data:`MODEL_OVERLAP_FACTOR` x
  ``AlignConfig.min_overlap_ratio``, residual at most ``max_residual_ratio`` x the noise),
  with tight support from at least two verified scans (so not a single partner);
* neither free-space test conflicts with a supporting scan
  (:func:`mvreg.globalstage.conflicts.free_space_conflicts`, the pairwise limits as they are:
  the pose was refined by ICP on the model);
* no degree of freedom is left open: not a fit on one plane of the model
  (:func:`mvreg.globalstage.probes.on_one_plane`: a scene's ground fits a scan at any
  heading), no continuous one (:func:`~mvreg.globalstage.probes.degenerate_direction`)
  and no second, distant pose that fits as well
  (:func:`mvreg.globalstage.model_search.distant_alternative`, which also tries the scan
  moved by the model's near-symmetries: where the scan's few descriptors give RANSAC no
  distant motion at all, a placement on the turned copy of a near-symmetric part would
  otherwise meet no rival. featuretype sparse seed 1 with ``--seed 0``: scan_004 placed
  179 deg off, overlap 0.41; the turn found its true place at 0.81).

Scans split off together (``groups``: parts of the pair graph cut where views
contradicted each other) are also tried at their group's motions onto the model.
Placed scans join the model for the next ones (rounds until none is added). Their poses
come from the scan-to-model ICP; the pipeline then refines them with the others by one
joint ICP (:meth:`mvreg.globalstage.stage.GlobalStage.run_verified`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from mvreg.config.align import AlignConfig
from mvreg.executor import single_threaded_blas
from mvreg.geometry import invert_transform, transform_points
from mvreg.globalstage.conflicts import free_space_conflicts
from mvreg.globalstage.model_search import (
    FeatureModel,
    distant_alternative,
    feature_model,
    motion_candidates,
    pair_poses,
    principal_turns,
    share_on,
)
from mvreg.globalstage.probes import degenerate_direction, on_one_plane
from mvreg.globalstage.scan_model import MODEL_SCANS, Overlaps, model_fit, scan_model
from mvreg.globalstage.verify import ScanVerification
from mvreg.pairwise.hypotheses import distinct_poses, same_pose, scan_extent
from mvreg.pairwise.icp import feature_level_tree, icp_point_to_plane, icp_trimmed

MODEL_OVERLAP_FACTOR = 2.0
"""A pose the model alone confirms stands in for a cycle, so it must cover more of the
scan than one unconfirmed pair needs: at least this many times the pairwise minimum
overlap. On 28 generalization runs of machined parts (sparse and dense, seeds 0-1) the
placements that passed every other test 4-146 deg off covered 0.11-0.16 of their scan,
the right ones 0.52-0.97."""

# Descriptor-free starts (rotation_candidates): scan points ICP'd per start, iterations,
# anchors (the most populated cells), and how many scans get them per run (each once).
START_POINTS = 150
START_ITERATIONS = 5
START_ANCHORS = 24
START_SCANS = 8
# A group's descriptor-free starts kept (each tried on every scan of the group, once): the
# right one is rarely the best fit when the group overlaps the model little.
GROUP_STARTS = 48
BASIN_STARTS = 3  # starts per basin refined (:func:`_try`)
TURNED_PROPOSALS = 4  # best proposals turned by the model's near-symmetries (_place_one)
FIRST_STAGE_POINTS = 2000  # fine points in the wide first ICP stage of a placement


@dataclass
class LeftoverSearches:
    """What earlier calls of :func:`place_leftovers` searched in vain, kept across the
    passes of a run: ``failed`` = {scan: (its key, the placed scans it failed against)}.

    A scan whose key is unchanged (:meth:`key`: its pair results and its group) is searched
    again only once a pair partner of it is placed that was not placed then: the same
    search against the same scans repeats itself (the 60-station scene: the second pass
    searched all its leftovers again, in full, and placed none)."""

    failed: dict[int, tuple[str, frozenset]] = field(default_factory=dict)

    @staticmethod
    def key(s: int, results=(), group: dict | None = None) -> str:
        """A digest of what a search of scan ``s`` starts from besides the placed scans:
        its pair results (pair, acceptance, pose and every hypothesis) and the members of
        its group ({scan: T_world_scan} or None; not their poses, which each pass solves
        again to within its noise)."""
        h = hashlib.sha1()
        for r in results:
            if s not in (r.i, r.j):
                continue
            h.update(f"{r.i},{r.j},{r.accepted};".encode())
            hyps = [T for T, _ in r.stats.get("accepted_hypotheses", [])]
            for T in [r.T_i_j, *r.stats.get("pose_hypotheses", []), *hyps]:
                h.update(np.ascontiguousarray(T, dtype=np.float64).tobytes())
        h.update(f"group {sorted(group or {})}".encode())
        return h.hexdigest()


def place_leftovers(
    pre,
    T_verified: dict[int, np.ndarray],
    todo,
    voxel: float,
    acfg: AlignConfig,
    results=(),
    max_tries: int = 6,
    groups=(),
    searched: LeftoverSearches | None = None,
) -> dict[int, tuple[np.ndarray, ScanVerification]]:
    """Scans of ``todo`` placed on the model of the verified scans (module docstring).

    Candidate poses: RANSAC of the scan on the model, and every pose hypothesis of the
    pair results (``results``: ``PairResult``, accepted or not; ``T_i_j``,
    ``stats["pose_hypotheses"]`` and every hypothesis the pair's aligner accepted,
    ``stats["accepted_hypotheses"]``) between the scan and a placed scan, carried into the
    world frame by that scan's pose. Those that bring the most of the scan's feature points
    onto the model are refined per scan and round, ``max_tries`` basins (:func:`_try`).
    Where none passes, the descriptor-free starts (:func:`rotation_candidates`), for at
    most ``START_SCANS`` scans per call, each once.

    ``groups``: [{scan: T_world_scan}], scans whose relative poses their own pairs fix
    (parts of the pair graph split off where views contradicted each other). A group's
    scans are also tried at the group's motions: the poses of its union on the model
    (:func:`motion_candidates` and :func:`rotation_candidates` of the union, once per
    group: a group covers more of the object than any of its scans), and the motion of
    a group mate already placed. Each scan must still pass :func:`_check` on its own.

    Large runs (more than ``MODEL_SCANS`` + 1 placed scans): a scan with a placed pair
    partner is searched against its partners and the placed scans facing them
    (:func:`_model_scans`), and tries at most ``max_tries`` of its group's searched
    motions, so each search costs the same however many scans are placed.

    ``searched``: a :class:`LeftoverSearches` kept across calls (the passes of a run),
    read and updated: a scan that failed with the same key is not searched again until
    a pair partner of it not placed then is placed."""
    searched = LeftoverSearches() if searched is None else searched
    with single_threaded_blas():  # small SVDs and solves: threads only busy-wait
        return _place_all(
            pre, T_verified, todo, voxel, acfg, results, max_tries, groups, searched
        )  # fmt: skip


def _place_all(pre, T_verified, todo, voxel, acfg, results, max_tries, groups, searched):
    placed: dict[int, tuple[np.ndarray, ScanVerification]] = {}
    T_all = dict(T_verified)
    todo = [s for s in todo if s not in T_all]
    models: dict[tuple, list] = {}  # the placed set -> [feature model, fine model, turns]
    started: set[int] = set()  # scans that had the descriptor-free starts (once each)
    group_of = {s: g for g in groups if len(g) >= 2 for s in g}
    motions: dict[tuple, list] = {}  # a group's motions onto the model (searched once)
    grouped: set[int] = set()  # scans that had their group's searched motions
    partners = _partners(results, groups)
    # The placed set each scan last failed against; none yet, so a scan is first searched
    # once some pair partner of it is placed.
    paired = {k for r in results for k in (r.i, r.j)}
    failed_on: dict[int, frozenset] = {s: frozenset() for s in todo if s in paired}
    keys = {s: LeftoverSearches.key(s, results, group_of.get(s)) for s in todo}
    for s in todo:  # what an earlier call searched in vain from the same start
        if s in searched.failed and searched.failed[s][0] == keys[s]:
            failed_on[s] = searched.failed[s][1]
    near: dict = {}  # the placed set's Overlaps (large runs, :func:`_model_scans`)
    while todo and len(T_all) >= 2:
        added = []
        for s in todo:
            if s in failed_on and not (partners.get(s, set()) & (T_all.keys() - failed_on[s])):
                continue  # none of its pair partners placed since: the same search again
            key = _model_scans(s, pre, T_all, partners, voxel, near)
            if key not in models:  # rebuilt only when a scan was placed (or another place)
                models = {key: [feature_model(pre, T_all, key), scan_model(pre, T_all, key)]}
            starts = s not in started and len(started) < START_SCANS
            group = group_of.get(s)
            extra = _group_poses(s, group, pre, T_all, models[key][0], voxel, acfg, motions)
            if group is not None and (s in grouped or len(key) < len(T_all)):
                # Its group's search once per scan; in a large run (its model bounded to
                # where its pairs say it lies) only the first max_tries of it, as many as
                # its own basins: a scene's groups tried ~65 basins per scan at ~0.3 s each.
                mates = len([k for k in group if k in T_all])
                extra = extra[: mates + (0 if s in grouped else max_tries)]
            grouped.add(s)
            T_near = {k: T_all[k] for k in key}
            found, tried = _place_one(
                s, pre, T_near, models[key], voxel, acfg, results, max_tries, starts, extra
            )  # fmt: skip
            if tried:
                started.add(s)
            if found is not None:
                T_all[s] = found[0]
                placed[s] = found
                added.append(s)
            else:
                failed_on[s] = frozenset(T_all)
                searched.failed[s] = (keys[s], failed_on[s])
        if not added:
            break
        todo = [s for s in todo if s not in added]
    return placed


def _model_scans(s, pre, T_all, partners, voxel, near) -> tuple[int, ...]:
    """The placed scans that scan ``s`` is searched against: all of them up to
    ``MODEL_SCANS`` + 1; beyond, its placed pair partners and the placed scans that face
    them (:class:`mvreg.globalstage.scan_model.Overlaps`), at most ``MODEL_SCANS`` in
    all, as a verified scan's model (:func:`mvreg.globalstage.scan_model.model_members`).
    Where its pairs say it lies is where it can be placed; a search against every placed
    scan costs each of a scene's leftovers the whole scene. ``near``: a cache, {key:
    Overlaps of the placed set}."""
    placed = tuple(sorted(T_all))
    mine = sorted(partners.get(s, set()) & T_all.keys())
    if len(placed) <= MODEL_SCANS + 1 or not mine:
        return placed
    if placed not in near:
        near.clear()
        near[placed] = Overlaps(pre, T_all, 2.0 * voxel)
    overlaps = near[placed]
    mine = overlaps.facing(mine, placed, MODEL_SCANS)  # each shares all its own cells
    rest = [k for k in placed if k not in mine]
    return tuple(sorted(mine + overlaps.facing(rest, mine, MODEL_SCANS - len(mine))))


def _partners(results, groups) -> dict[int, set[int]]:
    """{scan: the scans it was paired with (a pair result, accepted or not) or grouped
    with}. A scan is searched only once one of these is placed, and after failing, again
    only once another one was: the model then covers where its pairs said it might
    overlap, and their hypotheses carry into the world only through a placed partner. Up
    to ``pairs.all_pairs_max_scans`` scans every pair is tried, so any placement counts;
    above it only the candidate pairs (a 60-station scene: every leftover searched after
    each placement took over 18 min). A scan with no pair result at all (none given) is
    searched from the start; a group mate placed counts for searching again."""
    out: dict[int, set[int]] = {}
    for r in results:
        out.setdefault(r.i, set()).add(r.j)
        out.setdefault(r.j, set()).add(r.i)
    for g in groups:
        for s in g:
            out.setdefault(s, set()).update(k for k in g if k != s)
    return out


def _group_poses(s, group, pre, T_all, target, voxel, acfg, motions) -> list[np.ndarray]:
    """Poses of scan ``s`` from its group's motions (:func:`place_leftovers`): those of the
    mates already placed first, then those of the group's search on the model."""
    if group is None:
        return []
    out = [T_all[k] @ invert_transform(group[k]) @ group[s] for k in group if k in T_all]
    key = tuple(sorted(group))
    if key not in motions:
        source = feature_model(pre, group, key)
        found = motion_candidates(target, source, acfg, voxel, seed=key[0], far=-1.0, guided=True)
        motions[key] = found + rotation_candidates(source, target, voxel, acfg, GROUP_STARTS)
    return out + [M @ group[s] for M in motions[key]]


def _place_one(s, pre, T_all, models, voxel, acfg, results, max_tries, starts, extra=()):
    """(pose and verification of scan ``s`` on the model, or None; whether the
    descriptor-free starts were tried). ``starts``: they may be. ``extra``: candidate
    poses tried first (a group's motions)."""
    target = models[0]
    source = feature_model(pre, {s: np.eye(4)}, [s])
    if len(source.points) < 3 or len(target.points) < 3:
        return None, False
    if extra:  # every one of them: the group's best fit is often not the right one
        found = _try(s, extra, source, pre, T_all, models, voxel, acfg, len(extra), results)
        if found is not None:
            return found, False
    # Descriptor candidates first; where none passes, starts that need no descriptors.
    candidates = pair_poses(s, results, T_all, accepted=True)
    if len(source.features) >= 3 and len(target.features) >= 3:
        # No pose to stay away from: far = -1 keeps every match.
        candidates += motion_candidates(
            target, source, acfg, voxel, seed=s, far=-1.0, guided=True
        )  # fmt: skip
    found = _try(s, candidates, source, pre, T_all, models, voxel, acfg, max_tries, results)
    if found is None and candidates:
        # The same proposals turned by the model's near-symmetries: on a near-symmetric
        # part they all fall on the turned copy, which the free-space tests refuse
        # (featuretype sparse seed 1: every start of the scans cut off 150-180 deg away).
        first = _distinct_best(candidates, source, target, voxel, acfg)[:TURNED_PROPOSALS]
        turned = [S @ C for S in _turns(models, voxel, acfg) for C in first]
        found = _try(s, turned, source, pre, T_all, models, voxel, acfg, max_tries, results)
    if found is not None or not starts:
        return found, False
    cands = rotation_candidates(source, target, voxel, acfg, 4 * max_tries)
    return _try(s, cands, source, pre, T_all, models, voxel, acfg, max_tries, results), True


def _try(s, candidates, source, pre, T_all, models, voxel, acfg, max_tries, results=()):
    """The first candidate, in order of the share of the scan they bring onto the model,
    that passes :func:`_check` after ICP on the fine level (last trimmed to the noise:
    :func:`mvreg.pairwise.icp.icp_trimmed`): (T, verification) or None. At most
    ``max_tries`` basins of the first ICP stage are refined and checked (a start landing in
    a basin already tried is skipped), from at most ``BASIN_STARTS`` x as many distinct
    starts. ``results``: the pair results, whose hypotheses :func:`_check` tries as second
    poses."""
    if not candidates:
        return None
    target, model = models[0], models[1]
    members = sorted(T_all)
    best = _distinct_best(candidates, source, target, voxel, acfg)
    centre, radius = scan_extent(source.points)
    scan = pre[s]
    reach = (acfg.ransac_distance_voxels + 1.0) * voxel
    # Last, only the matches within the tight residual of the noise pull (the scan's
    # overlap): the points beyond it, within a voxel of some other surface, drag a scan
    # that overlaps the model little off its place (featuretype dense seed 1: 0.6 deg off
    # trimmed, 3.8 deg untrimmed, from a start at 0.8 deg or at the true pose).
    tight = acfg.tight_residual_ratio * 0.5 * (scan.noise + float(np.median(model.noise)))
    # The wide first ICP stage on an even subset of the fine points (the cost is in it);
    # starts that end in a basin already tried are not refined again.
    sub = np.unique(np.linspace(0, len(scan.fine_points) - 1, FIRST_STAGE_POINTS).astype(int))
    # ``max_tries`` basins, from at most ``BASIN_STARTS`` x as many starts: on a
    # near-symmetric part the best-covered starts all fall into the turned copy's basin.
    tried: list[np.ndarray] = []
    for C in best[: BASIN_STARTS * max_tries]:
        if len(tried) == max_tries:
            break
        T = icp_point_to_plane(
            scan.fine_points[sub], scan.fine_normals[sub], model.points, model.normals,
            model.tree, C, reach, 50, acfg.icp_min_normal_cos,
        )  # fmt: skip
        if any(same_pose(T, K, voxel, centre, radius) for K in tried):
            continue
        tried.append(T)
        T = icp_point_to_plane(
            scan.fine_points, scan.fine_normals, model.points, model.normals, model.tree,
            T, voxel, 30, acfg.icp_min_normal_cos,
        )  # fmt: skip
        T = icp_trimmed(
            scan.fine_points, scan.fine_normals, model.points, model.normals, model.tree,
            T, voxel, tight, acfg.icp_min_normal_cos,
        )  # fmt: skip
        v = _check(s, T, pre, T_all, members, model, voxel, acfg, results, models)
        if v is not None:
            return T, v
    return None


def _distinct_best(candidates, source, target, voxel, acfg) -> list[np.ndarray]:
    """``candidates`` in order of the share of ``source`` they bring onto ``target``, no
    two within 3 voxels of each other."""
    shares = [share_on(target, source, C, acfg, voxel) for C in candidates]
    order = np.argsort(-np.asarray(shares), kind="stable")
    centre, radius = scan_extent(source.points)
    return distinct_poses([candidates[k] for k in order], 3 * voxel, centre, radius)


def rotation_candidates(
    source: FeatureModel, target: FeatureModel, voxel: float, acfg: AlignConfig, keep: int,
    max_points: int = START_POINTS, iterations: int = START_ITERATIONS,
    max_anchors: int = START_ANCHORS,
) -> list[np.ndarray]:  # fmt: skip
    """Poses of ``source`` on ``target`` found without descriptors: the 60 rotations of the
    icosahedral group (none farther than ~40 deg from any rotation), each with the scan's
    centroid put at every anchor (the mean of the model's points in cells of 3/4 the scan's
    radius: wherever on the model the scan may lie; the ``max_anchors`` most populated
    cells), refined by a few point-to-plane ICP
    iterations on an even subset of the scan's feature points. Returns the ``keep`` that
    bring most of that subset within the RANSAC inlier distance of the model, best first,
    no two within ~30 deg of each other (:func:`distinct_poses`).
    """
    centre, radius = scan_extent(source.points)
    idx = np.linspace(0, len(source.points) - 1, min(max_points, len(source.points)))
    idx = np.unique(idx.astype(np.int64))
    pts, nrm = source.points[idx], source.normals[idx]
    cell = 0.75 * radius
    _, inv = np.unique(np.floor(target.points / cell).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.ravel()
    count = np.bincount(inv)
    anchors = np.stack([np.bincount(inv, weights=target.points[:, a]) / count for a in range(3)], 1)
    anchors = anchors[np.argsort(-count, kind="stable")[:max_anchors]]
    tree = feature_level_tree(target)
    reach = (acfg.ransac_distance_voxels + 1.0) * voxel
    limit = acfg.ransac_distance_voxels * voxel
    scored = []
    for R in Rotation.create_group("I").as_matrix():
        for a in anchors:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, a - R @ centre
            T = icp_point_to_plane(
                pts, nrm, target.points, target.normals, tree, T, reach, iterations,
                acfg.icp_min_normal_cos,
            )  # fmt: skip
            d, _ = tree.query(transform_points(T, pts), distance_upper_bound=limit)
            scored.append((float(np.mean(np.isfinite(d))), T))
    # Distinct by a turn of ~30 deg (half the radius): ICP from nearby starts often stops
    # short of the same basin, and one basin would fill every slot.
    kept: list[np.ndarray] = []
    for k in np.argsort([-sc for sc, _ in scored], kind="stable"):
        T = scored[k][1]
        if not any(same_pose(T, K, 0.5 * radius, centre, radius) for K in kept):
            kept.append(T)
            if len(kept) == keep:
                break
    return kept


def _turns(models: list, voxel, acfg) -> list[np.ndarray]:
    """The near-symmetries of the placed set (``models``: [feature model, fine model],
    then these, computed once per model: :func:`principal_turns`)."""
    if len(models) == 2:
        models.append(principal_turns(models[1], voxel, acfg))
    return models[2]


def _check(s, T, pre, T_all, members, model, voxel, acfg, results=(), models=None):
    """The verification of scan ``s`` placed at ``T`` (a ScanVerification), or None when it
    fails (module docstring). Second poses are also sought among the hypotheses of the
    scan's pairs in ``results`` (:func:`pair_poses`): a scan placed 15 deg off on a part
    the model covers twice passed every other test while its pairs held the true pose;
    and at the near-symmetries of ``models`` (:func:`_turns`), when given."""
    names = [p.name for p in pre]
    pts = transform_points(T, pre[s].fine_points)
    nrm = pre[s].fine_normals @ T[:3, :3].T
    overlap, ratio, tight, idx, noise = model_fit(model, pts, nrm, pre[s].noise, voxel, acfg)
    if overlap < MODEL_OVERLAP_FACTOR * acfg.min_overlap_ratio:
        return None
    if not ratio <= acfg.max_residual_ratio:
        return None
    owners, counts = np.unique(model.owner[idx[tight]], return_counts=True)
    support = [int(k) for k, n in zip(owners, counts, strict=True) if n >= acfg.min_correspondences]
    if len(support) < 2:
        return None
    v = ScanVerification(
        status="verified", evidence="model search", model_overlap=overlap,
        model_residual_ratio=ratio, supporting_scans=[names[k] for k in support],
    )  # fmt: skip
    with_s = {**T_all, s: T}
    # The pairwise limits as they are: ICP on the model has refined this pose (a scan
    # placed ~10 deg off on a planar part shows 0.02 of its points where a supporting scan
    # saw nothing; at its true pose, none).
    strict = acfg.model_copy(update={"coarse_gate_slack": 1.0})
    if free_space_conflicts(v, s, members, support, pre, with_s, names, strict):
        return None
    if on_one_plane(model, pts, nrm, tight, idx, voxel) is not None:
        return None
    if degenerate_direction(model, pts, nrm, tight, idx, noise, voxel, acfg) is not None:
        return None
    turns = () if models is None else _turns(models, voxel, acfg)
    alt = distant_alternative(
        [s], pre, with_s, members, model, voxel, acfg, results=results, turns=turns
    )  # fmt: skip
    if alt is not None:
        return None
    v.reason = "placed by a search against the model of the verified scans"
    return v
