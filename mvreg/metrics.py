"""Gauge-free error metrics against ground truth.

Poses are only defined up to one global rigid motion (the gauge), so estimates are first
aligned to the truth by the best global rotation (and translation), then compared.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mvreg.errors import InputError
from mvreg.geometry import project_to_orthogonal, rotation_angle_deg


def best_global_rotation(R_est: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """Q in SO(d) minimizing sum ||Q R_est_i - R_true_i||_F^2. Inputs (M, d, d)."""
    return project_to_orthogonal(np.einsum("mij,mkj->ik", R_true, R_est)[None])[0]


def rotation_errors_deg(R_est: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """(M,) angle (degrees) between Q R_est_i and R_true_i after the best global Q."""
    q = best_global_rotation(R_est, R_true)
    return rotation_angle_deg(np.einsum("mji,jk,mkl->mil", R_true, q, R_est))


def translation_errors(
    R_est: np.ndarray, t_est: np.ndarray, R_true: np.ndarray, t_true: np.ndarray
) -> np.ndarray:
    """(M,) ||Q t_est_i + c - t_true_i|| after the best global rotation Q and shift c."""
    q = best_global_rotation(R_est, R_true)
    moved = t_est @ q.T
    c = np.mean(t_true - moved, axis=0)
    return np.linalg.norm(moved + c - t_true, axis=1)


@dataclass
class PoseErrors:
    """Per-patch errors after gauge alignment (rotation in degrees, translation in units)."""

    rotation_deg: np.ndarray
    translation: np.ndarray

    def summary(self) -> dict:
        return {
            "rotation_deg_median": float(np.median(self.rotation_deg)),
            "rotation_deg_max": float(np.max(self.rotation_deg)),
            "translation_median": float(np.median(self.translation)),
            "translation_max": float(np.max(self.translation)),
        }


def _check_poses(T_est: np.ndarray, T_true: np.ndarray) -> None:
    if T_est.shape != T_true.shape:
        raise InputError(f"estimated poses {T_est.shape} and true poses {T_true.shape} differ")
    if T_est.ndim != 3 or T_est.shape[0] == 0 or T_est.shape[1:] not in ((3, 3), (4, 4)):
        raise InputError(f"poses must be an (M, d+1, d+1) stack with M >= 1, got {T_est.shape}")
    if not (np.all(np.isfinite(T_est)) and np.all(np.isfinite(T_true))):
        raise InputError("poses have NaN or inf")


def pose_errors(T_est: np.ndarray, T_true: np.ndarray, at: np.ndarray | None = None) -> PoseErrors:
    """Errors of (M, d+1, d+1) world_from_local estimates against the truth.

    Translation errors are those of each local frame's origin, or, with ``at`` ((M, d)
    points in the local frames, e.g. each scan's centroid), of those points: the same as
    moving each local origin there first. A local origin far from the data (a scanner
    two object sizes away, or a random frame) turns a small rotation error into a large
    origin error; the error at the centroid is where the scan's points actually are.
    """
    T_est, T_true = np.asarray(T_est, dtype=np.float64), np.asarray(T_true, dtype=np.float64)
    _check_poses(T_est, T_true)
    d = T_est.shape[-1] - 1
    r_e, t_e = T_est[:, :d, :d], T_est[:, :d, d]
    r_t, t_t = T_true[:, :d, :d], T_true[:, :d, d]
    if at is not None:
        t_e = t_e + np.einsum("mij,mj->mi", r_e, at)
        t_t = t_t + np.einsum("mij,mj->mi", r_t, at)
    return PoseErrors(rotation_errors_deg(r_e, r_t), translation_errors(r_e, t_e, r_t, t_t))


def overlap_residual(
    points_world: list[np.ndarray], max_distance: float, max_points: int = 5000, seed: int = 0
) -> dict:
    """Nearest-neighbour distances between overlapping scans after alignment.

    For each scan, (up to ``max_points`` of) its points are matched to the nearest point of
    any other scan; those closer than ``max_distance`` count as overlapping. Returns the
    median and mean distance over all overlapping points, the overlapping fraction, and
    per-scan medians. Compare two alignments of the same data with the same arguments.
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    union = cKDTree(np.concatenate(points_world)) if points_world else None
    # Owner of each union point; one more entry (-1) for the index of "no neighbour".
    owner = np.concatenate([np.full(len(p), i) for i, p in enumerate(points_world)] + [[-1]])
    all_d, per_scan = [], []
    total = 0
    for i, p in enumerate(points_world):
        q = p if len(p) <= max_points else p[rng.choice(len(p), max_points, replace=False)]
        best = _nearest_of_others(union, owner, i, q, max_distance)
        ok = best < max_distance
        total += len(q)
        all_d.append(best[ok])
        per_scan.append(float(np.median(best[ok])) if np.any(ok) else None)
    return residual_summary(all_d, total, per_scan, max_distance)


def _nearest_of_others(union, owner, i, q, max_distance: float) -> np.ndarray:
    """Distance from each of ``q`` to the nearest point of ``union`` not owned by scan
    ``i`` (inf beyond ``max_distance``): the k nearest, k growing for the points whose k
    nearest within reach are all scan ``i``'s own (one union tree instead of one query per
    other scan: linear in the scans, not quadratic)."""
    best = np.full(len(q), np.inf)
    todo = np.arange(len(q))
    k = 8
    while len(todo):
        k = min(k, len(owner) - 1)
        d, idx = union.query(q[todo], k=k, distance_upper_bound=max_distance)
        d, idx = d.reshape(len(todo), -1), idx.reshape(len(todo), -1)
        others = np.where(owner[idx] == i, np.inf, d)
        best[todo] = others.min(axis=1)
        # Unresolved: no other scan among the k, and the k-th is still within reach.
        unresolved = np.isinf(best[todo]) & np.isfinite(d[:, -1])
        if k >= len(owner) - 1:
            break
        todo, k = todo[unresolved], 8 * k
    return best


def residual_summary(all_d: list, total: int, per_scan: list, max_distance: float) -> dict:
    """The overlap-residual dict from the matched distances of each scan: median, mean,
    the share of the ``total`` query points that found a match, and per-scan medians."""
    d = np.concatenate(all_d) if all_d else np.zeros(0)
    return {
        "median": float(np.median(d)) if d.size else None,
        "mean": float(np.mean(d)) if d.size else None,
        "overlap_fraction": float(d.size / max(total, 1)),
        "max_distance": float(max_distance),
        "per_scan_median": per_scan,
    }
