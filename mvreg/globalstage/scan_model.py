"""The union of the registered scans' fine levels in the world frame, and how well one
scan's points fit it (shared by :mod:`mvreg.globalstage.verify` and
:mod:`mvreg.globalstage.model_search`).

Contract: :func:`scan_model` builds the :class:`ScanModel` of some scans under their poses;
:func:`model_members` chooses, per scan, the other scans a check of it runs against (all of
them up to :data:`MODEL_SCANS`, else those covering most of its surface, so the checks'
cost grows with the scans, not their square);
:class:`Overlaps` says which scans share surface, to bound the searches of large runs to
the scans near the one searched;
:func:`model_fit` scores world points with normals on it (overlap share of tight matches,
median point-to-plane residual over the scans' noise, which model points matched);
:func:`equally_good` says whether one pose's score is as good as another's within the
sampling spread.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mvreg.config.align import AlignConfig
from mvreg.geometry import transform_points

MODEL_SCANS = 24
"""A scan is checked against at most this many others (its largest overlaps; as many as
the joint ICP's partners): the model of 24 scans that share the most of its surface covers
it as well as the model of all (issue 14: 80 builtin scans, verification 120 s -> see
docs/benchmarks/scale.md)."""


def cell_sharing(world: Sequence[np.ndarray], cell: float) -> tuple[np.ndarray, np.ndarray]:
    """(shared (n, n), size (n,)): how many cells of side ``cell`` each two point sets of
    ``world`` both occupy, and how many each occupies."""
    import scipy.sparse as sp

    cells = [np.unique(np.floor(w / cell).astype(np.int64), axis=0) for w in world]
    _, ids = np.unique(np.concatenate(cells), axis=0, return_inverse=True)
    rows = np.repeat(np.arange(len(cells)), [len(c) for c in cells])
    occ = sp.csr_matrix((np.ones(len(ids)), (rows, ids.ravel())), shape=(len(cells), ids.max() + 1))
    shared = (occ @ occ.T).toarray()
    return shared, np.diag(shared).copy()


def model_members(
    pre, T_world_scan, cell: float, k: int = MODEL_SCANS, near: Overlaps | None = None
) -> dict[int, list[int]]:
    """{scan: the other registered scans it is checked against}: all of them when there
    are at most ``k``, else the ``k`` that occupy the largest share of its cells of side
    ``cell`` (ties: lower index), sorted. ``near``: the :class:`Overlaps` of these poses
    at that cell, when the caller has it."""
    scans = sorted(T_world_scan)
    if len(scans) - 1 <= k:
        return {s: [o for o in scans if o != s] for s in scans}
    near = Overlaps(pre, T_world_scan, cell) if near is None else near
    out = {}
    for a, s in enumerate(scans):
        frac = near.frac[a].copy()
        frac[a] = -1.0
        order = np.lexsort((np.arange(len(scans)), -frac))[:k]
        out[s] = sorted(scans[b] for b in order)
    return out


class Overlaps:
    """Which registered scans share surface under their poses: the share of each scan's
    cells of side ``cell`` (feature level) that each other scan occupies too. Computed once
    per set of poses; :meth:`facing` bounds a search across a bridge or around a leftover
    scan's partners to the scans near it (a scene of many stations: each overlaps only its
    neighbours, and a search against all of them costs the scans squared)."""

    def __init__(self, pre, T_world_scan, cell: float):
        self.scans = sorted(T_world_scan)
        self.index = {s: a for a, s in enumerate(self.scans)}
        world = [transform_points(T_world_scan[s], pre[s].points) for s in self.scans]
        shared, size = cell_sharing(world, cell)
        self.frac = shared / np.maximum(size, 1.0)[:, None]

    def facing(self, scans, others, k: int = MODEL_SCANS) -> list[int]:
        """The scans of ``scans`` that share cells with some scan of ``others``, at most
        ``k`` (the largest summed shares, ties: lower index), sorted."""
        scans, others = sorted(scans), sorted(others)
        if not scans or not others or k <= 0:
            return []
        ia = [self.index[s] for s in scans]
        share = self.frac[np.ix_(ia, [self.index[o] for o in others])].sum(axis=1)
        order = np.lexsort((np.arange(len(scans)), -share))[:k]
        return sorted(scans[a] for a in order if share[a] > 0)


@dataclass
class ScanModel:
    points: np.ndarray
    normals: np.ndarray
    owner: np.ndarray  # scan index of each model point
    noise: np.ndarray  # that scan's noise estimate
    tree: cKDTree


def scan_model(pre, T_world_scan, members) -> ScanModel | None:
    members = [k for k in members if k in T_world_scan]
    if not members:
        return None
    pts, nrm, own, noi = [], [], [], []
    for k in members:
        T = T_world_scan[k]
        pts.append(transform_points(T, pre[k].fine_points))
        nrm.append(pre[k].fine_normals @ T[:3, :3].T)
        own.append(np.full(len(pre[k].fine_points), k))
        noi.append(np.full(len(pre[k].fine_points), pre[k].noise))
    p = np.concatenate(pts)
    # Built for one check and queried once or a few times: the unbalanced tree builds in
    # half the time and answers the same (exact nearest neighbours).
    tree = cKDTree(p, balanced_tree=False, compact_nodes=False)
    return ScanModel(p, np.concatenate(nrm), np.concatenate(own), np.concatenate(noi), tree)


def match(model: ScanModel, pts, nrm, max_dist, min_cos):
    """Nearest model point within ``max_dist`` with agreeing normal: (index or -1,
    point-to-plane residual or inf)."""
    d, nn = model.tree.query(pts, distance_upper_bound=max_dist)
    idx = np.full(len(pts), -1, np.int64)
    res = np.full(len(pts), np.inf)
    found = np.flatnonzero(np.isfinite(d))
    k = nn[found]
    ok = np.einsum("ij,ij->i", model.normals[k], nrm[found]) >= min_cos
    found, k = found[ok], k[ok]
    idx[found] = k
    res[found] = np.abs(np.einsum("ij,ij->i", model.normals[k], pts[found] - model.points[k]))
    return idx, res


def model_fit(model, pts, nrm, noise_s, voxel, acfg: AlignConfig):
    """Overlap share, residual ratio, tight matches (mask), model indices, noise."""
    idx, res = match(model, pts, nrm, acfg.score_distance_voxels * voxel, acfg.score_min_normal_cos)
    has = idx >= 0
    noise = 0.5 * (noise_s + (np.median(model.noise[idx[has]]) if np.any(has) else noise_s))
    tight = res <= acfg.tight_residual_ratio * noise
    overlap = float(np.mean(tight)) if len(pts) else 0.0
    ratio = float(np.median(res[has]) / noise) if np.any(has) else float("inf")
    return overlap, ratio, tight, idx, noise


def overlap_spread(share: float, n: int) -> float:
    """Three binomial standard errors of an overlap ``share`` measured over ``n`` points:
    how far two shares may differ by the sampling alone."""
    return 3.0 * np.sqrt(max(share * (1 - share), 1e-12) / max(n, 1))


def equally_good(overlap, ratio, base_overlap, base_ratio, n, acfg: AlignConfig) -> bool:
    """Whether a probed pose fits the model as well as the final one: residual within the
    acceptance rule and no worse than the final one's by more than its sampling spread,
    overlap share no lower than the final one's by more than its sampling spread (binomial
    standard error, times 3, over the ``n`` probed points) plus a tenth (the probe
    moves the border of the overlap)."""
    if not ratio <= acfg.max_residual_ratio:
        return False
    spread = overlap_spread(base_overlap, n)
    if overlap < base_overlap * 0.9 - spread:
        return False
    return ratio <= base_ratio * 1.25 + 3.0 / np.sqrt(max(n, 1))


def normal_matrix(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """6x6 point-to-plane normal matrix per point of matched (points, model normals),
    rotation about the points' centroid scaled by their rms radius ``L``: rows
    ``[((p - c) x n) / L, n]``. Returns (H, c, L)."""
    c = points.mean(axis=0)
    q = points - c
    L = float(np.sqrt(np.mean(np.sum(q * q, axis=1)))) + 1e-300
    a = np.concatenate([np.cross(q, normals) / L, normals], axis=1)
    return a.T @ a / max(len(a), 1), c, L
