"""Joint point-to-plane ICP over all poses at once, the last step of refinement.

Takes the preprocessed scans, a :class:`GlobalSolution` (certified poses), the ``refine``
and ``robust`` sections and plain values (normal agreement, feature voxel, executor);
returns the solution with new poses and a log. Every overlapping pair contributes only
point-to-plane residuals n . (T_world_j p - T_world_i q), so a direction one pair leaves
free (two scans sharing a plane and a cylinder) is set by the pairs that constrain it.
All poses move together by Gauss-Newton (Cauchy-weighted residuals, pair weights as in
the robust rounds, the first registered scan fixed), correspondences recomputed each
iteration. The normals are re-estimated on the union of the registered scans
(:func:`model_normals`; ``refine.joint_icp_model_normals``): the union is denser than any
one view, and normals of sparse views bias the residuals. They are estimated at the start
poses, and once the iterations converge, again at those poses and the iterations rerun
(the union of scans still off by a few tenths of a degree blurs them), unless they moved
no point by more than the scans' noise (the union was aligned to within it already).

The objective is not the certified one, so the step starts from the certified solution
and the log says how far it moved every scan; a result that moves any scan further than
``RefineConfig.joint_icp_max_move_voxels`` is not kept (the certified poses stay).
Measurements behind this design: docs/design/globalstage.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from mvreg.config.refine import RefineConfig
from mvreg.config.robust import RobustConfig
from mvreg.executor import Executor
from mvreg.geometry import (
    cross3,
    invert_transform,
    rotation_angle_deg,
    rotation_from_vector,
    transform_points,
)
from mvreg.globalstage.refine import overlapping_pairs
from mvreg.globalstage.robust import robust_weights
from mvreg.pairwise import PreprocessedScan

JOINT_ICP_MAX_PARTNERS = 24
"""Each scan chooses at most this many partners (its largest overlaps) for the joint ICP,
so its pairs grow with the scans, not with their square. More than the rounds'
:data:`~mvreg.globalstage.refine.MAX_PARTNERS`: the final poses average over these
residuals (issue 14, 40 builtin scans: 12 partners 0.089 deg worst, 24 partners 0.068,
every overlapping pair 0.069; 80 scans: 24 partners 0.074, 32 partners 0.072, every pair
0.077)."""

NEIGHBOURS = 30
"""Fewest neighbours of a point in the union of the scans its normal comes from
(:func:`model_normals`); Open3D's estimate for one scan takes at most as many
(``preprocess.normal_max_neighbours``)."""

MAX_NEIGHBOURS = 150
"""Most neighbours :func:`model_normals` takes to reach its radius in a dense union."""

NORMAL_REACH = 1.5
"""The neighbourhood of a model normal reaches at least this many joint ICP correspondence
distances (:func:`neighbours_for`)."""


@dataclass
class _Terms:
    """One pair's point-to-plane rows under the current poses (centred world frame)."""

    i: int
    j: int
    b: np.ndarray  # (n, 3) source points of scan j, world minus centre
    a: np.ndarray  # (n, 3) their matches in scan i, world minus centre
    n: np.ndarray  # (n, 3) world normals of the matches
    r: np.ndarray  # (n,) signed point-to-plane residuals


def neighbours_for(world: np.ndarray, radius: float, sample: int = 2000) -> int:
    """How many nearest points of the union ``world`` reach ``radius``: :data:`NEIGHBOURS`
    scaled by the area (radius / the median distance to the NEIGHBOURS-th neighbour over
    up to ``sample`` evenly strided points) squared, between NEIGHBOURS and
    :data:`MAX_NEIGHBOURS`.

    Why a reach, not a count: the normals are estimated at poses still off by up to a
    correspondence distance, so where one scan's sheet lies offset from the others', a
    neighbourhood smaller than the offset tilts the normals into agreeing with it and the
    joint ICP stops there (fandisk dense seed 0: 30 neighbours of the dense union reach
    0.48 voxels; one view slid 0.53 voxels along a weakly held direction stayed 0.49
    voxels off, while point-to-plane ICP against the others alone takes it to 0.02; 73
    neighbours, 0.75 voxels: 0.07). A sparse union (3,000-point views) already reaches
    it with NEIGHBOURS."""
    from scipy.spatial import cKDTree

    if len(world) <= MAX_NEIGHBOURS:
        return min(NEIGHBOURS, max(3, len(world) - 1))
    probe = world[:: max(1, len(world) // sample)]
    d, _ = cKDTree(world).query(probe, [NEIGHBOURS + 1], workers=-1)
    reach = float(np.median(d[:, 0]))
    if not reach > 0.0:
        return NEIGHBOURS
    return int(np.clip(np.ceil(NEIGHBOURS * (radius / reach) ** 2), NEIGHBOURS, MAX_NEIGHBOURS))


def model_normals(points, normals, T_world_scan: dict, radius: float) -> list:
    """Each registered scan's normals re-estimated on the union of the registered scans.

    ``points``/``normals``: per scan, in its frame (the level the joint ICP matches);
    ``T_world_scan``: the poses to merge them at. The normal of a point is the direction of
    least spread of its nearest points of the union (as many as reach ``radius``:
    :func:`neighbours_for`; estimated on a sample of the union with the same reach:
    :func:`union_normals`), turned back into the scan's frame with the sign of its own
    normal. Where views overlap, the union is several times denser than one scan: a sparse
    view (3,000 points) holds ~4 of its own points within the normal radius of the dense
    level, and normals of so few noisy points bias point-to-plane residuals (idler_riser
    sparse seed 0: the joint ICP took the worst scan from 0.17 to 0.74 deg with the scans'
    own normals, to 0.17 with these; from the true poses, sparse busted and spot views drift
    0.40-0.45 and 0.14-0.17 deg with their own normals, 0.10-0.11 and 0.03-0.06 with these).
    Dense views are unchanged (fandisk and cow, 20,000 points: 0.03-0.05 deg either way).
    Cost: one KNN normal estimate over a sample of the registered points and a nearest-point
    query of all of them (:func:`joint_icp` calls it once or twice). Scans without a pose
    keep theirs. Measurements: docs/design/globalstage.md."""
    scans = sorted(T_world_scan)
    world = [transform_points(T_world_scan[s], points[s]) for s in scans]
    union = np.concatenate(world)
    merged = union_normals(union, neighbours_for(union, radius))
    out = list(normals)
    start = 0
    for s, w in zip(scans, world, strict=True):
        n = merged[start : start + len(w)] @ T_world_scan[s][:3, :3]  # into the scan's frame
        start += len(w)
        flip = np.einsum("ij,ij->i", n, normals[s]) < 0
        n[flip] *= -1.0
        out[s] = n
    return out


def union_normals(union: np.ndarray, k: int) -> np.ndarray:
    """Unit normals (unsigned) of the points ``union``: the direction of least spread of
    the ``k`` nearest points; for ``k`` above :data:`NEIGHBOURS`, of the NEIGHBOURS nearest
    among every ``k / NEIGHBOURS``-th point (the same reach).

    Why not ``k`` neighbours of every point: the cost grows with ``k`` (210,000 points of
    the ten real bunny scans, k = 105: 2.7 and 2.3 s for the two estimates of a joint ICP
    with Open3D, 1.7 and 1.4 s so), while the reach is what the estimate needs. On 210,000
    noisy samples of the bunny mesh (k = 101), the angle to the mesh's faces: median 4.1 deg
    with k neighbours, 4.8 deg so, 5.6 deg with 30 neighbours of every point."""
    import open3d as o3d

    if k <= NEIGHBOURS:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(union))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
        return np.asarray(pcd.normals)
    from scipy.spatial import cKDTree

    keep = np.unique(np.floor(np.arange(0.0, len(union), k / NEIGHBOURS)).astype(np.int64))
    centred = union - union.mean(axis=0)  # second moments about a point near the data
    sample = centred[keep]
    _, near = cKDTree(sample).query(centred, NEIGHBOURS, workers=-1)
    # First and second moments of each point's NEIGHBOURS samples, summed sample by sample.
    moments = np.concatenate([sample, (sample[:, :, None] * sample[:, None, :]).reshape(-1, 9)], 1)
    acc = np.zeros((len(union), 12))
    for c in range(NEIGHBOURS):
        acc += moments[near[:, c]]
    mean = acc[:, :3] / NEIGHBOURS
    cov = acc[:, 3:].reshape(-1, 3, 3) / NEIGHBOURS - mean[:, :, None] * mean[:, None, :]
    return np.linalg.eigh(cov)[1][:, :, 0]


def _scan_terms(group, T, points, normals, trees, strides, max_dist, min_cos, centre):
    """The terms of every pair (i, j) of ``group`` = (i, [j, ...]): the sources of all of
    scan i's partners matched in one KD-tree query (the same matches as one query per
    pair, at a fraction of the calls: 200 scans of 400 points have 2,400 pairs)."""
    i, js = group
    T_i = invert_transform(T[i])
    rel = [T_i @ T[j] for j in js]
    src = [points[j][:: strides[j]] for j in js]
    q = [transform_points(T_i_j, p) for T_i_j, p in zip(rel, src, strict=True)]
    d, nn = trees[i].query(np.concatenate(q), distance_upper_bound=max_dist)
    T_c = T[i].copy()
    T_c[:3, 3] -= centre  # world frame shifted to the centre
    out, start = [], 0
    for j, T_i_j, p in zip(js, rel, src, strict=True):
        dj, kj = d[start : start + len(p)], nn[start : start + len(p)]
        start += len(p)
        ok = np.flatnonzero(np.isfinite(dj))
        k = kj[ok]
        n_src = normals[j][:: strides[j]][ok] @ T_i_j[:3, :3].T
        agree = np.einsum("ij,ij->i", normals[i][k], n_src) >= min_cos
        ok, k = ok[agree], k[agree]
        b = transform_points(T_c @ T_i_j, p[ok])
        a = transform_points(T_c, points[i][k])
        n = normals[i][k] @ T[i][:3, :3].T
        out.append(_Terms(i, j, b, a, n, np.einsum("ij,ij->i", b - a, n)))
    return out


def _gauss_newton_step(terms, pair_w, c, col, radius) -> np.ndarray:
    """Solve the (sparse, block-structured) normal equations of the weighted residuals.

    Unknowns per scan in ``col``: (w * radius, v), a turn w about the centre and a shift v;
    a pair touches only its two scans' 6 x 6 blocks, so the system stays sparse for
    thousands of scans. The Jacobian rows of all pairs are formed at once and each pair's
    12 x 12 block by one product.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    n = 6 * len(col)
    live = [(t, w) for t in terms if (w := pair_w.get((t.i, t.j), 0.0)) != 0.0 and len(t.r)]
    if not live:
        return np.zeros(n)
    counts = np.array([len(t.r) for t, _ in live])
    b, a, nrm, r = (np.concatenate([getattr(t, f) for t, _ in live]) for f in "banr")
    # Cauchy weights times the pair's weight
    wt = np.repeat([w for _, w in live], counts) / (1.0 + (r / c) ** 2)
    # d r / d (w_j * radius, v_j) and d r / d (w_i * radius, v_i), side by side
    jac = np.empty((len(r), 12))
    jac[:, :3] = cross3(b, nrm) / radius
    jac[:, 3:6] = nrm
    jac[:, 6:9] = -cross3(a, nrm) / radius
    jac[:, 9:] = -nrm
    wjac = jac * wt[:, None]
    ends = np.cumsum(counts)
    blocks = np.empty((len(live), 12, 12))
    grads = np.empty((len(live), 12))
    for k, (e, m) in enumerate(zip(ends, counts, strict=True)):
        blocks[k] = wjac[e - m : e].T @ jac[e - m : e]
        grads[k] = wjac[e - m : e].T @ r[e - m : e]
    six = np.arange(6)
    idx = np.array(
        [
            np.concatenate([col[t.j] + six if t.j in col else -1 - six,
                            col[t.i] + six if t.i in col else -1 - six])
            for t, _ in live
        ]
    )  # fmt: skip
    g = np.zeros(n)
    ok = idx >= 0
    np.add.at(g, idx[ok], grads[ok])
    both = ok[:, :, None] & ok[:, None, :]
    rows = np.broadcast_to(idx[:, :, None], blocks.shape)[both]
    cols = np.broadcast_to(idx[:, None, :], blocks.shape)[both]
    H = sp.csc_matrix((blocks[both], (rows, cols)), shape=(n, n))
    # A direction no pair constrains (a scan held only by a plane) gets a zero step.
    damping = 1e-9 * float(H.diagonal().sum()) / n + 1e-300
    return spsolve(H + damping * sp.identity(n, format="csc"), -g)


def joint_icp(
    pre: Sequence[PreprocessedScan],
    sol,
    cfg: RefineConfig,
    robust: RobustConfig,
    min_normal_cos: float,
    voxel: float,
    executor: Executor,
    levels=None,
    pairs: Sequence[tuple[int, int]] | None = None,
):
    """Refine all poses of ``sol`` (a GlobalSolution) jointly by point-to-plane ICP.

    ``levels``: (points, normals, KD-trees) per scan to match (the dense refinement level;
    default the fine points). ``pairs``: scan pairs to use (default registered pairs whose
    world bounding boxes overlap, at most :data:`JOINT_ICP_MAX_PARTNERS` chosen per scan).
    Returns (GlobalSolution with the new poses and the same solve result, log dict); the
    log says whether the new poses were kept (``accepted``) and how far they moved each
    scan. (sol, None) when there is nothing to do.
    """
    T0 = {int(k): np.array(v, dtype=np.float64) for k, v in sol.T_world_scan.items()}
    scans = sorted(T0)
    if cfg.joint_icp_iterations == 0 or len(scans) < 2:
        return sol, None
    if levels is None:
        levels = (
            [p.fine_points for p in pre],
            [p.fine_normals for p in pre],
            [p.fine_tree() for p in pre],
        )
    max_dist = cfg.joint_icp_distance_voxels * voxel
    cand = (
        overlapping_pairs(pre, T0, max_dist, JOINT_ICP_MAX_PARTNERS)
        if pairs is None
        else [(i, j) for i, j in pairs if i in T0 and j in T0]
    )
    strides = {
        s: max(1, int(np.ceil(len(levels[0][s]) / cfg.joint_icp_points_per_pair))) for s in scans
    }
    world0 = {s: transform_points(T0[s], pre[s].points) for s in scans}
    centre = np.mean([w.mean(0) for w in world0.values()], axis=0)
    radius = max(float(np.max(np.linalg.norm(w - centre, axis=1))) for w in world0.values())

    groups: dict[int, list[int]] = {}
    for i, j in cand:
        groups.setdefault(i, []).append(j)
    order = {p: k for k, p in enumerate(cand)}

    def terms_with(level):
        def terms_of(T):
            def one(g):
                return _scan_terms(g, T, *level, strides, max_dist, min_normal_cos, centre)

            terms = [t for ts in executor.map(one, list(groups.items())) for t in ts]
            terms.sort(key=lambda t: order[(t.i, t.j)])  # the pairs' order, as before
            return [t for t in terms if len(t.r) >= cfg.min_correspondences]

        return terms_of

    own = levels[1]
    if cfg.joint_icp_model_normals:  # normals from the union, at the start poses
        levels = (levels[0], model_normals(levels[0], own, T0, NORMAL_REACH * max_dist), levels[2])
    limit = (world0, cfg.joint_icp_max_move_voxels * voxel)
    T, log, final = _iterate(T0, scans, terms_with(levels), cfg, robust, voxel, centre, radius,
                             limit)  # fmt: skip
    # Once more from the union so aligned, unless the first pass moved every point by less
    # than the scans' noise: the union it estimated the normals on was then already aligned
    # to within the noise, and a second estimate changes nothing that matters (80 builtin
    # scans: 0.06 voxels moved; a sparse start 0.8 deg off moves several noise widths).
    noise = float(np.median([pre[s].noise for s in scans]))
    log["iterations_model_normals"] = 0
    if cfg.joint_icp_model_normals and final and not log["beyond_limit"]:
        if _max_move(T, T0, world0) > noise:
            levels = (levels[0], model_normals(levels[0], own, T, NORMAL_REACH * max_dist),
                      levels[2])  # fmt: skip
            T, again, final = _iterate(T, scans, terms_with(levels), cfg, robust, voxel, centre,
                                       radius, limit, T0)  # fmt: skip
            log["iterations_model_normals"] = again["iterations"]
            log["beyond_limit"] = again["beyond_limit"]
    log["residual_median_end"] = (
        float(np.median(np.abs(np.concatenate([t.r for t in final])))) if final else None
    )
    _moves(log, T, T0, world0, voxel)
    log["accepted"] = bool(log["max_point_move_voxels"] <= cfg.joint_icp_max_move_voxels)
    if not log["accepted"]:
        return sol, log
    return replace(sol, T_world_scan={s: T[s] for s in scans}), log


def _iterate(T0, scans, terms_of, cfg: RefineConfig, robust, voxel, centre, radius, limit,
             T_start=None):  # fmt: skip
    """Gauss-Newton iterations from T0; (poses, log, the final terms).

    ``limit`` = (points per scan in the world at ``T_start`` (default T0), largest move):
    the iterations stop as soon as a scan's points have moved further than that from
    ``T_start`` (``log["beyond_limit"]``): the result would not be kept, and the scan that
    slides along what its pairs leave free keeps sliding (200 scans of 400 points: 30
    iterations, 45 s, for a result then refused)."""
    col = {s: 6 * k for k, s in enumerate(scans[1:])}  # the first scan is held fixed
    T = dict(T0)
    T_start = T0 if T_start is None else T_start
    world0, max_move = limit
    pair_w: dict[tuple[int, int], float] = {}
    log = {"pairs": 0, "iterations": 0, "residual_median_start": None, "beyond_limit": False}
    for it in range(cfg.joint_icp_iterations):
        terms = terms_of(T)
        if not terms:
            break
        r_all = np.abs(np.concatenate([t.r for t in terms]))
        if it == 0:  # pair weights from the pairs' residuals, as in the robust rounds
            med = np.array([float(np.median(np.abs(t.r))) for t in terms])
            w = robust_weights(med, voxel, robust)
            pair_w = {(t.i, t.j): float(wk) for t, wk in zip(terms, w, strict=True)}
            log["pairs"] = int(np.count_nonzero(w))
            log["residual_median_start"] = float(np.median(r_all))
        # Cauchy scale: 3 robust standard deviations of the residuals.
        c = max(3.0 * 1.4826 * float(np.median(r_all)), 1e-6 * voxel)
        step = _gauss_newton_step(terms, pair_w, c, col, radius)
        moved = 0.0
        for s, o in col.items():
            w_rot, v = step[o : o + 3] / radius, step[o + 3 : o + 6]
            D = np.eye(4)
            D[:3, :3] = rotation_from_vector(w_rot)
            D[:3, 3] = v + centre - D[:3, :3] @ centre  # turn about the centre
            T[s] = D @ T[s]
            moved = max(moved, float(np.linalg.norm(w_rot)) * radius + float(np.linalg.norm(v)))
        log["iterations"] = it + 1
        if moved < cfg.joint_icp_tolerance_voxels * voxel:
            break
        if _max_move(T, T_start, world0) > max_move:
            log["beyond_limit"] = True
            break
    return T, log, terms_of(T)


def _displacement(T, T0, world0, s) -> float:
    """The largest displacement of scan ``s``'s points between poses T0 and T."""
    w = world0[s]
    return float(
        np.max(np.linalg.norm(transform_points(T[s] @ invert_transform(T0[s]), w) - w, axis=1))
    )


def _max_move(T, T0, world0) -> float:
    """The largest displacement of any scan point between poses T0 and T."""
    return max(_displacement(T, T0, world0, s) for s in world0)


def _moves(log: dict, T, T0, world0, voxel: float) -> None:
    """How far each scan moved: rotation, and the largest displacement of its points."""
    rot = {
        s: float(rotation_angle_deg((T[s] @ invert_transform(T0[s]))[None, :3, :3])[0]) for s in T0
    }
    disp = {s: _displacement(T, T0, world0, s) for s in T0}
    log["max_rotation_change_deg"] = max(rot.values())
    log["max_point_move"] = max(disp.values())
    log["max_point_move_voxels"] = max(disp.values()) / voxel
