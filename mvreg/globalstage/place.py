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
  model of many scans few mutual matches are right) and point-to-plane ICP on the fine
  level bring it to a pose whose overlap share and residual pass the pairwise acceptance
  rule (``AlignConfig.min_overlap_ratio``, ``max_residual_ratio`` x the noise), with tight
  support from at least two verified scans (so not a single partner);
* neither free-space test conflicts with a supporting scan
  (:func:`mvreg.globalstage.verify.free_space_conflicts`, the pairwise limits loosened by
  ``coarse_gate_slack``);
* no degree of freedom is left open: no continuous one
  (:func:`mvreg.globalstage.probes.degenerate_direction`) and no second, distant pose that
  fits as well (:func:`mvreg.globalstage.model_search.distant_alternative`).

Placed scans join the model for the next ones (rounds until none is added). Their poses
come from the scan-to-model ICP and are not re-solved with the others.
"""

from __future__ import annotations

import numpy as np

from mvreg.config.align import AlignConfig
from mvreg.executor import single_threaded_blas
from mvreg.geometry import transform_points
from mvreg.globalstage.model_search import (
    distant_alternative,
    feature_model,
    motion_candidates,
    pair_poses,
    share_on,
)
from mvreg.globalstage.probes import degenerate_direction
from mvreg.globalstage.scan_model import model_fit, scan_model
from mvreg.globalstage.verify import ScanVerification, free_space_conflicts
from mvreg.pairwise.hypotheses import distinct_poses, scan_extent
from mvreg.pairwise.icp import icp_point_to_plane


def place_leftovers(
    pre,
    T_verified: dict[int, np.ndarray],
    todo,
    voxel: float,
    acfg: AlignConfig,
    results=(),
    max_tries: int = 6,
) -> dict[int, tuple[np.ndarray, ScanVerification]]:
    """Scans of ``todo`` placed on the model of the verified scans (module docstring).

    Candidate poses: RANSAC of the scan on the model, and every pose hypothesis of the
    pair results (``results``: ``PairResult``, accepted or not; ``T_i_j`` and
    ``stats["pose_hypotheses"]``) between the scan and a placed scan, carried into the
    world frame by that scan's pose. The ``max_tries`` that bring the most of the scan's
    feature points onto the model are refined per scan and round."""
    with single_threaded_blas():  # small SVDs and solves: threads only busy-wait
        return _place_all(pre, T_verified, todo, voxel, acfg, results, max_tries)


def _place_all(pre, T_verified, todo, voxel, acfg, results, max_tries):
    placed: dict[int, tuple[np.ndarray, ScanVerification]] = {}
    T_all = dict(T_verified)
    todo = [s for s in todo if s not in T_all]
    models: dict[tuple, tuple] = {}  # the placed set -> (feature model, fine model)
    while todo and len(T_all) >= 2:
        added = []
        for s in todo:
            key = tuple(sorted(T_all))
            if key not in models:  # rebuilt only when a scan was placed
                models = {key: (feature_model(pre, T_all, key), scan_model(pre, T_all, key))}
            found = _place_one(s, pre, T_all, models[key], voxel, acfg, results, max_tries)
            if found is not None:
                T_all[s] = found[0]
                placed[s] = found
                added.append(s)
        if not added:
            break
        todo = [s for s in todo if s not in added]
    return placed


def _place_one(s, pre, T_all, models, voxel, acfg, results, max_tries):
    members = sorted(T_all)
    target, model = models
    source = feature_model(pre, {s: np.eye(4)}, [s])
    if len(source.features) < 3 or len(target.features) < 3:
        return None
    # No pose to stay away from: far = -1 keeps every match.
    candidates = pair_poses(s, results, T_all)
    candidates += motion_candidates(target, source, acfg, voxel, seed=s, far=-1.0, guided=True)
    if not candidates:
        return None
    shares = [share_on(target, source, C, acfg, voxel) for C in candidates]
    order = np.argsort(-np.asarray(shares), kind="stable")
    centre, radius = scan_extent(source.points)
    best = distinct_poses([candidates[k] for k in order], 3 * voxel, centre, radius)
    scan = pre[s]
    reach = (acfg.ransac_distance_voxels + 1.0) * voxel
    for C in best[:max_tries]:
        T = C
        for dist, iters in ((reach, 50), (voxel, 30)):
            T = icp_point_to_plane(
                scan.fine_points, scan.fine_normals, model.points, model.normals, model.tree,
                T, dist, iters, acfg.icp_min_normal_cos,
            )  # fmt: skip
        v = _check(s, T, pre, T_all, members, model, voxel, acfg)
        if v is not None:
            return T, v
    return None


def _check(s, T, pre, T_all, members, model, voxel, acfg) -> ScanVerification | None:
    """The verification of scan ``s`` placed at ``T``, or None when it fails (module
    docstring)."""
    names = [p.name for p in pre]
    pts = transform_points(T, pre[s].fine_points)
    nrm = pre[s].fine_normals @ T[:3, :3].T
    overlap, ratio, tight, idx, noise = model_fit(model, pts, nrm, pre[s].noise, voxel, acfg)
    if overlap < acfg.min_overlap_ratio or not ratio <= acfg.max_residual_ratio:
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
    if free_space_conflicts(v, s, members, support, pre, with_s, names, acfg):
        return None
    if degenerate_direction(model, pts, nrm, tight, idx, noise, voxel, acfg) is not None:
        return None
    if distant_alternative([s], pre, with_s, members, model, voxel, acfg) is not None:
        return None
    v.reason = "placed by a search against the model of the verified scans"
    return v
