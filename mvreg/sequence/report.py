"""Evaluation of a sequence: overlap residual over the pair graph, errors against the
ground truth, and the drift report (KISS-ICP alone against the global solve).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mvreg.geometry import invert_transform, rotation_angle_deg, transform_points
from mvreg.metrics import pose_errors, residual_summary
from mvreg.pipeline.evaluate import truth_errors
from mvreg.sequence.odometry import kiss_version


def evaluate_sequence(reg, pre, results, truth) -> None:
    """Overlap residual over the pair graph; errors against ground truth when given.

    The overlap residual of ``register`` compares every scan with every other one; for a
    long sequence each scan is compared with its partners in the accepted pairs only.
    """
    if not reg.T_world_scan:
        return
    idx = {s.name: i for i, s in enumerate(reg.scans)}
    spacing = float(np.median([p.noise for p in pre]))
    thresh = max(2.0 * pre[0].fine_voxel_size, 10 * spacing)
    reg.overlap = graph_overlap(reg, idx, results, thresh)
    reg.truth_errors = truth_errors(reg, truth)


def graph_overlap(reg, idx, results, thresh: float, max_points: int = 2000) -> dict:
    partners: dict[int, set[int]] = {}
    for r in results:
        if r.accepted:
            partners.setdefault(r.i, set()).add(r.j)
            partners.setdefault(r.j, set()).add(r.i)
    rng = np.random.default_rng(reg.config.seed)
    registered = {idx[n] for n in reg.T_world_scan}
    world = {}

    def in_world(k: int) -> np.ndarray:
        if k not in world:
            p = reg.scans[k].points
            if len(p) > max_points:
                p = p[rng.choice(len(p), max_points, replace=False)]
            world[k] = transform_points(reg.T_world_scan[reg.scan_names[k]], p)
        return world[k]

    all_d, per_scan, total = [], [], 0
    for k in range(len(reg.scans)):
        others = [o for o in sorted(partners.get(k, ())) if o in registered]
        if k not in registered or not others:
            per_scan.append(None)
            continue
        q = in_world(k)
        d, _ = cKDTree(np.vstack([in_world(o) for o in others])).query(
            q, distance_upper_bound=thresh
        )
        ok = np.isfinite(d)
        total += len(q)
        all_d.append(d[ok])
        per_scan.append(float(np.median(d[ok])) if np.any(ok) else None)
    return {
        **residual_summary(all_d, total, per_scan, thresh),
        "compared_with": "partners in accepted pairs",
    }


def end_to_start_error(T_first: np.ndarray, T_last: np.ndarray, T_first_last_ref: np.ndarray):
    """Position (data units) and rotation (degrees) error of the last scan seen from the
    first: ``inv(T_first) @ T_last`` against the reference ``T_first_last_ref`` (4, 4)."""
    rel = invert_transform(T_first) @ T_last
    err = invert_transform(T_first_last_ref) @ rel
    return (
        float(np.linalg.norm(rel[:3, 3] - T_first_last_ref[:3, 3])),
        float(rotation_angle_deg(err[:3, :3])),
    )


def drift_report(reg, results, truth) -> dict:
    """KISS-ICP's drift and what the global solve leaves (see the module docstring)."""
    names = reg.scan_names
    odo = reg.T_odom_scan
    registered = [n for n in names if n in reg.T_world_scan]
    out: dict = {}
    steps = np.diff(np.stack([odo[n][:3, 3] for n in names]), axis=0)
    out["odometry_path_length"] = float(np.sum(np.linalg.norm(steps, axis=1)))
    if len(registered) >= 2:
        first, last = registered[0], registered[-1]
        out["first"], out["last"] = first, last
        if truth and first in truth and last in truth:
            ref = invert_transform(np.asarray(truth[first])) @ np.asarray(truth[last])
            t_path = np.stack([np.asarray(truth[n])[:3, 3] for n in names if n in truth])
            out["truth_path_length"] = float(
                np.sum(np.linalg.norm(np.diff(t_path, axis=0), axis=1))
            )
            e_o, r_o = end_to_start_error(odo[first], odo[last], ref)
            e_g, r_g = end_to_start_error(reg.T_world_scan[first], reg.T_world_scan[last], ref)
            out |= {
                "odometry_end_to_start_vs_truth": e_o,
                "odometry_end_to_start_rotation_deg_vs_truth": r_o,
                "global_end_to_start_vs_truth": e_g,
                "global_end_to_start_rotation_deg_vs_truth": r_g,
                "reduction_vs_truth": e_o / e_g if e_g > 0 else float("inf"),
            }
            common = [n for n in names if n in truth]
            err = pose_errors(
                np.stack([odo[n] for n in common]), np.stack([np.asarray(truth[n]) for n in common])
            )
            out["odometry_vs_truth"] = err.summary()
    # A verified loop closure joining the end of the sequence to its start.
    m = len(names)
    margin = max(1, m // 10)
    closing = [
        r
        for r in results
        if r.accepted and r.stats.get("kind") == "loop" and r.i < margin and r.j >= m - margin
    ]
    out["closed_loop"] = bool(closing)
    if closing:
        r = min(closing, key=lambda r: r.i + (m - 1 - r.j))
        a, b = names[r.i], names[r.j]
        out["loop_pair"] = [a, b]
        e_o, r_o = end_to_start_error(odo[a], odo[b], r.T_i_j)
        out["odometry_end_to_start_vs_loop_closure"] = e_o
        out["odometry_end_to_start_rotation_deg_vs_loop_closure"] = r_o
        if a in reg.T_world_scan and b in reg.T_world_scan:
            e_g, r_g = end_to_start_error(reg.T_world_scan[a], reg.T_world_scan[b], r.T_i_j)
            out["global_end_to_start_vs_loop_closure"] = e_g
            out["global_end_to_start_rotation_deg_vs_loop_closure"] = r_g
    return out


def sequence_report(
    reg, seq, odom, time_source, gaps, results, loops, noise, truth,
    warnings,
) -> dict:  # fmt: skip
    names = reg.scan_names
    by_kind: dict[str, dict] = {}
    for r in results:
        k = by_kind.setdefault(
            r.stats.get("kind", ""),
            {"tried": 0, "accepted": 0, "feature_ransac": 0, "accepted_from": {}, "rejected": []},
        )
        k["tried"] += 1
        if r.accepted:
            k["accepted"] += 1
            init = r.stats.get("init", "")
            k["feature_ransac"] += init == "feature RANSAC"
            k["accepted_from"][init] = k["accepted_from"].get(init, 0) + 1
        else:
            k["rejected"].append(list(r.names))
    for g in gaps:
        g["after"], g["before"] = names[g["after"]], names[g["after"] + 1]
    loop_stats = by_kind.get("loop", {"tried": 0, "accepted": 0})
    return {
        "timestamp_source": time_source,
        "gaps": gaps,
        "odometry": {
            "backend": "kiss-icp",
            "version": kiss_version(),
            "max_range": odom.max_range,
            "voxel_size": odom.voxel_size,
            "seconds": odom.seconds,
            "config": odom.config,
        },
        "settings": seq.model_dump(mode="json"),
        "residual_reference": noise,
        "pairs_by_kind": by_kind,
        "loop_closures": {
            "radius": loops.radius,
            "candidates": len(loops.candidates),
            "accepted": loop_stats["accepted"],
        },
        "drift": drift_report(reg, results, truth),
        "warnings": warnings,
    }
