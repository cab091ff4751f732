"""Point-to-plane ICP between two scans, and nearest neighbours with agreeing normals.

Takes two preprocessed scans (or plain point and normal arrays) and an initial
``T_i_j`` (4, 4, scan j into scan i's frame); returns the refined ``T_i_j``. Distances
are given in data units or, for the scan-level helpers, as multiples of the run's
feature voxel ``voxel`` (:class:`mvreg.scales.Scales`). Deterministic (NumPy and SciPy
KD-trees, no random choices); KD-trees of a scan are built once and cached on it.

* :func:`icp_point_to_plane`: the ICP itself, on arrays.
* :func:`coarse_icp`: on the feature level (``icp_coarse_distance_voxels``).
* :func:`fine_icp`: on the fine level, one run per distance, at most
  ``icp_max_source_points`` source points.
* :func:`nearest_with_normals`: per point, the nearest point of the other scan within a
  distance whose normal agrees, and the residual to its tangent plane.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from mvreg.config.align import AlignConfig
from mvreg.geometry import cross3, norm2, rotation_from_vector, transform_points
from mvreg.pairwise.preprocess import PreprocessedScan


def feature_level_tree(pre: PreprocessedScan) -> cKDTree:
    """KD-tree of the scan's feature-level points, cached on the scan."""
    if "tree" not in pre._cache:
        pre._cache["tree"] = cKDTree(pre.points)
    return pre._cache["tree"]


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
    max_residual: float | None = None,
) -> np.ndarray:
    """Point-to-plane ICP (Gauss-Newton on a linearised rotation), deterministic.

    Pairs each source point with its nearest target point within ``max_dist`` whose
    normal agrees (cosine >= ``min_normal_cos``) and, with ``max_residual``, whose
    point-to-plane distance is at most that (trimmed: points off the shared surface by
    more than the noise allows do not pull), minimises the squared distances to the
    target tangent planes, and stops when an update moves no point by more than
    ``tolerance * max_dist`` (changing correspondences make it jitter at small scales), or
    when it is back within that of the pose two steps before: two correspondence sets that
    each pull to the other's pose make a 2-cycle, which further steps only repeat.
    Returns the refined (4, 4) ``T_target_source``.
    """
    run = _IcpRun(source, source_normals, T_target_source, tolerance * max_dist)
    for _ in range(max_iterations):
        q = transform_points(run.T, source)
        d, nn = target_tree.query(q, distance_upper_bound=max_dist)
        run.step(q, d, nn, target, target_normals, min_normal_cos, max_residual)
        if run.done:
            break
    return run.T


def icp_point_to_plane_many(
    sources: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    target: np.ndarray,
    target_normals: np.ndarray,
    target_tree: cKDTree,
    max_dist: float,
    max_iterations: int = 30,
    min_normal_cos: float = 0.5,
    tolerance: float = 5e-3,
) -> list[np.ndarray]:
    """:func:`icp_point_to_plane` of several scans onto one target, the same poses as one
    call each: ``sources`` holds (points, normals, start ``T_target_source``) per scan. The
    scans still moving share one KD-tree query per iteration (a refinement round matches a
    scan with up to a dozen partners; on scans of a few hundred points the calls, not the
    queries, were the cost)."""
    runs = [_IcpRun(p, n, T, tolerance * max_dist) for p, n, T in sources]
    for _ in range(max_iterations):
        live = [(r, p) for r, (p, _, _) in zip(runs, sources, strict=True) if not r.done]
        if not live:
            break
        q = [transform_points(r.T, p) for r, p in live]
        d, nn = target_tree.query(np.concatenate(q), distance_upper_bound=max_dist)
        start = 0
        for (r, _), qk in zip(live, q, strict=True):
            end = start + len(qk)
            r.step(qk, d[start:end], nn[start:end], target, target_normals, min_normal_cos)
            start = end
    return [r.T for r in runs]


class _IcpRun:
    """One ICP's state between iterations: the pose, the two before it, done or not."""

    def __init__(self, source, source_normals, T_target_source, stop: float):
        self.source_normals = source_normals
        self.T = np.array(T_target_source, dtype=np.float64)
        self.extent = float(np.max(np.linalg.norm(source - source.mean(0), axis=1))) + 1e-300
        self.centroid = source.mean(0)
        self.stop = stop  # tolerance * max_dist
        self.before, self.previous = None, self.T  # the poses two steps and one step back
        self.done = False

    def distance(self, Ta, Tb) -> float:  # how far two poses put the source points apart
        turn = norm2(Ta[:3, :3] - Tb[:3, :3]) / np.sqrt(2.0)
        dR = Ta[:3, :3] - Tb[:3, :3]
        return turn * self.extent + norm2(dR @ self.centroid + Ta[:3, 3] - Tb[:3, 3])

    def step(self, q, d, nn, target, target_normals, min_normal_cos, max_residual=None):
        """One Gauss-Newton step from the matches (``d``, ``nn``) of the moved source ``q``."""
        T = self.T
        ok = np.flatnonzero(np.isfinite(d))
        if len(ok) < 6:
            self.done = True
            return
        n = target_normals[nn[ok]]
        agree = np.einsum("ij,ij->i", n, self.source_normals[ok] @ T[:3, :3].T) >= min_normal_cos
        ok, n = ok[agree], n[agree]
        if max_residual is not None:
            near = np.abs(np.einsum("ij,ij->i", q[ok] - target[nn[ok]], n)) <= max_residual
            ok, n = ok[near], n[near]
        if len(ok) < 6:
            self.done = True
            return
        x = _plane_step(q[ok], target[nn[ok]], n)
        if x is None:
            self.done = True
            return
        step = np.eye(4)
        step[:3, :3] = rotation_from_vector(x[:3])
        step[:3, 3] = x[3:]
        self.before, self.previous, self.T = self.previous, T, step @ T
        if norm2(x[:3]) * self.extent + norm2(x[3:]) < self.stop:
            self.done = True
        elif self.before is not None and self.distance(self.T, self.before) < self.stop:
            self.done = True


def icp_trimmed(
    source: np.ndarray,
    source_normals: np.ndarray,
    target: np.ndarray,
    target_normals: np.ndarray,
    target_tree: cKDTree,
    T_target_source: np.ndarray,
    max_dist: float,
    max_residual: float,
    min_normal_cos: float = 0.5,
    iterations: int = 10,
) -> np.ndarray:
    """:func:`icp_point_to_plane` within ``max_dist`` with the trimming residual halved
    from ``max_dist`` down to ``max_residual`` (``iterations`` each, three times as many
    at the last): points off the shared surface by more than the noise allows stop
    pulling, while a start the untrimmed matches left biased (by more than
    ``max_residual``) is brought back before the band narrows."""
    T, limit = T_target_source, max_dist
    while limit > max_residual:
        limit = max(0.5 * limit, max_residual)
        T = icp_point_to_plane(
            source, source_normals, target, target_normals, target_tree, T, max_dist,
            iterations * (3 if limit == max_residual else 1), min_normal_cos,
            max_residual=limit,
        )  # fmt: skip
    return T


def _plane_step(p: np.ndarray, target: np.ndarray, n: np.ndarray) -> np.ndarray | None:
    """The (6,) Gauss-Newton step (rotation vector, translation) moving points ``p`` onto
    the planes through ``target`` with normals ``n``; None when singular.

    Solved for a turn about the points' centroid with the lever arms divided by their
    RMS length, so rotation and translation columns have the same scale whatever the
    units and the distance from the origin (the damping is relative to them); returned
    as the same motion about the origin."""
    r = np.einsum("ij,ij->i", p - target, n)
    c = p.mean(0)
    arm = p - c
    scale = float(np.sqrt(np.mean(np.einsum("ij,ij->i", arm, arm)))) + 1e-300
    arm /= scale
    a = np.empty((len(p), 6))
    a[:, :3] = cross3(arm, n)
    a[:, 3:] = n
    ata = a.T @ a
    try:
        x = np.linalg.solve(ata + 1e-12 * np.trace(ata) * np.eye(6), -a.T @ r)
    except np.linalg.LinAlgError:
        return None
    w = x[:3] / scale  # p -> R (p - c) + c + u, as R p + (c - R c + u)
    return np.concatenate([w, c - rotation_from_vector(w) @ c + x[3:]])


def coarse_icp(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    T_i_j: np.ndarray,
    cfg: AlignConfig,
    voxel: float,
    iterations: int | None = None,
) -> np.ndarray:
    """Feature-level ICP of scan j onto scan i from ``T_i_j`` within
    ``cfg.icp_coarse_distance_voxels * voxel``, at most ``iterations`` iterations
    (default ``cfg.icp_max_iterations``)."""
    return icp_point_to_plane(
        pre_j.points, pre_j.normals, pre_i.points, pre_i.normals, feature_level_tree(pre_i),
        T_i_j, cfg.icp_coarse_distance_voxels * voxel,
        cfg.icp_max_iterations if iterations is None else iterations, cfg.icp_min_normal_cos,
    )  # fmt: skip


def fine_icp(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    T_i_j: np.ndarray,
    distances_voxels: Sequence[float],
    cfg: AlignConfig,
    voxel: float,
) -> np.ndarray:
    """Point-to-plane ICP on the fine level, one run per distance (in feature voxels
    ``voxel``), from ``T_i_j`` (4, 4); at most ``cfg.icp_max_source_points`` source points."""
    stride = max(1, int(np.ceil(len(pre_j.fine_points) / cfg.icp_max_source_points)))
    src, src_n = pre_j.fine_points[::stride], pre_j.fine_normals[::stride]
    T = np.asarray(T_i_j, dtype=np.float64)
    for dist in distances_voxels:
        T = icp_point_to_plane(
            src, src_n, pre_i.fine_points, pre_i.fine_normals, pre_i.fine_tree(),
            T, dist * voxel, cfg.icp_max_iterations, cfg.icp_min_normal_cos,
        )  # fmt: skip
    return T


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


def icp_point_to_plane_batch(
    source: np.ndarray,
    source_normals: np.ndarray,
    target: np.ndarray,
    target_normals: np.ndarray,
    target_tree: cKDTree,
    T_target_source: np.ndarray,
    max_dist: float,
    iterations: int,
    min_normal_cos: float = 0.5,
    workers: int = 1,
    tolerance: float = 5e-3,
) -> np.ndarray:
    """:func:`icp_point_to_plane` from many start poses at once: (K, 4, 4) in, (K, 4, 4)
    out. Each start takes the same Gauss-Newton steps as there, at most ``iterations``,
    and stops when a step moves no point by more than ``tolerance * max_dist``; a start
    with fewer than six correspondences keeps its pose. One KD-tree query per iteration for
    the starts still moving (on ``workers`` threads; deterministic), so hundreds of starts
    cost about as much as a few one at a time."""
    T = np.array(T_target_source, dtype=np.float64).reshape(-1, 4, 4).copy()
    n = len(source)
    extent = float(np.max(np.linalg.norm(source - source.mean(0), axis=1), initial=0.0))
    active = np.arange(len(T))
    for _ in range(iterations):
        if n == 0 or len(active) == 0:
            break
        Ta = T[active]
        k = len(Ta)
        q = np.matmul(source, Ta[:, :3, :3].transpose(0, 2, 1)) + Ta[:, None, :3, 3]
        d, nn = target_tree.query(q.reshape(-1, 3), distance_upper_bound=max_dist, workers=workers)
        ok = np.isfinite(d).reshape(k, n)
        nn = np.where(ok.ravel(), nn, 0).reshape(k, n)
        tn = target_normals[nn]
        sn = np.matmul(source_normals, Ta[:, :3, :3].transpose(0, 2, 1))
        w = (ok & (np.einsum("kni,kni->kn", tn, sn) >= min_normal_cos)).astype(np.float64)
        count = w.sum(1)
        r = np.einsum("kni,kni->kn", q - target[nn], tn)
        c = np.einsum("kn,kni->ki", w, q) / np.maximum(count, 1.0)[:, None]
        arm = q - c[:, None]
        scale = np.sqrt(np.einsum("kn,kni,kni->k", w, arm, arm) / np.maximum(count, 1.0)) + 1e-300
        arm /= scale[:, None, None]
        a = np.concatenate([np.cross(arm, tn), tn], axis=2)
        aw = a * w[..., None]
        ata = np.matmul(aw.transpose(0, 2, 1), a)
        atb = np.einsum("kni,kn->ki", aw, r)
        damp = 1e-12 * np.trace(ata, axis1=1, axis2=2) + 1e-300
        x = np.linalg.solve(ata + damp[:, None, None] * np.eye(6), -atb[..., None])[..., 0]
        x[count < 6] = 0.0
        wv = x[:, :3] / scale[:, None]  # p -> R (p - c) + c + u
        R = _rotations(wv)
        step = np.zeros((k, 4, 4))
        step[:, :3, :3] = R
        step[:, :3, 3] = c - np.einsum("kij,kj->ki", R, c) + x[:, 3:]
        step[:, 3, 3] = 1.0
        T[active] = np.matmul(step, Ta)
        moved = np.linalg.norm(wv, axis=1) * extent + np.linalg.norm(x[:, 3:], axis=1)
        active = active[(moved >= tolerance * max_dist) & (count >= 6)]
    return T


def _rotations(w: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotations of the rotation vectors ``w`` (K, 3), by Rodrigues."""
    theta = np.linalg.norm(w, axis=1)
    kx = np.zeros((len(w), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    kx -= np.transpose(kx, (0, 2, 1))
    safe = np.where(theta < 1e-12, 1.0, theta)
    unit = kx / safe[:, None, None]
    s = np.where(theta < 1e-12, 1.0, np.sin(theta))[:, None, None]
    c = np.where(theta < 1e-12, 0.0, 1.0 - np.cos(theta))[:, None, None]
    return np.eye(3) + s * unit + c * (unit @ unit)
