"""Evaluation of a registration: overlap residual of the raw points and, when a ground
truth is given, pose errors against it (gauge-free). Used only to report, never to solve.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from mvreg.geometry import transform_points
from mvreg.metrics import overlap_residual, pose_errors


def evaluate_overlap_and_truth(reg, pre, truth) -> None:
    """Overlap residual on the raw points; errors against ground truth when given (and
    the truth's names that no scan has, in ``reg.truth_without_scan``)."""
    known = set(reg.all_scan_names)
    reg.truth_without_scan = sorted(n for n in (truth or {}) if n not in known)
    if not reg.T_world_scan:
        return
    idx = {s.name: i for i, s in enumerate(reg.scans)}
    world = [transform_points(T, reg.scans[idx[n]].points) for n, T in reg.T_world_scan.items()]
    thresh = max(2.0 * reg.scales.fine_voxel, 10 * reg.scales.noise)
    common = [n for n in reg.T_world_scan if n in (truth or {})]
    truth_residual = None
    if len(common) >= 2:  # the truth's own residual on a second thread (same numbers)
        tw = [transform_points(np.asarray(truth[n]), reg.scans[idx[n]].points) for n in common]
        pool = ThreadPoolExecutor(1)
        truth_residual = pool.submit(
            overlap_residual, tw, thresh, max_points=2000, seed=reg.config.seed
        )
        pool.shutdown(wait=False)
    reg.overlap = overlap_residual(world, thresh, max_points=2000, seed=reg.config.seed)
    reg.truth_errors = truth_errors(reg, truth)
    if reg.truth_errors is not None:
        reg.truth_errors["truth_overlap_residual"] = truth_residual.result()
    reg.stored_pose_differences = stored_pose_differences(reg)


def stored_pose_differences(reg) -> dict | None:
    """How far the registered poses are from the poses the files store (E57 scan headers),
    gauge-free as against a ground truth (:func:`truth_errors`); None with fewer than 2
    registered scans that have one. Reported, never used to judge the result."""
    stored = {s.name: s.T_world_scan_hint for s in reg.scans if s.T_world_scan_hint is not None}
    return truth_errors(reg, stored)


def truth_errors(reg, truth) -> dict | None:
    """Errors of the registered poses against ``truth`` ({name: (4, 4)}), gauge-free:
    rotation (deg), translation at the frame origins and at the scan centroids (data
    units); None with fewer than 2 scans in common."""
    common = [n for n in reg.T_world_scan if n in (truth or {})]
    if len(common) < 2:
        return None
    idx = {s.name: i for i, s in enumerate(reg.scans)}
    est = np.stack([reg.T_world_scan[n] for n in common])
    tru = np.stack([np.asarray(truth[n]) for n in common])
    err = pose_errors(est, tru)
    centroids = np.stack([reg.scans[idx[n]].points.mean(axis=0) for n in common])
    at_centroid = pose_errors(est, tru, at=centroids).translation
    return {
        "scans": common,
        "rotation_deg": err.rotation_deg.tolist(),
        "translation": err.translation.tolist(),
        **err.summary(),
        "translation_at_centroid": at_centroid.tolist(),
        "translation_at_centroid_max": float(at_centroid.max()),
    }
