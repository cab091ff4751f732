"""Output folder of ``register``: poses (JSON, TUM, KITTI), merged cloud, report.

Every file is written atomically (temporary file, then rename): an interrupted run never
leaves a half-written file; :class:`mvreg.io.output_folder.OutputFolder` makes a whole
run's outputs one set (written aside, swapped in) and refuses folders that hold results.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvreg.geometry import transform_points
from mvreg.io.atomic import atomic_path, atomic_write_json
from mvreg.io.merged_formats import write_merged
from mvreg.io.poses import write_poses_json, write_poses_kitti, write_poses_tum


def merged_cloud(reg, voxel_size: float | None = None):
    """All registered scans in the world frame, colored per scan, voxel-downsampled.

    Returns (points (N, 3) float64 in the files' frame -- the local frame offset of a
    georeferenced input added back after downsampling --, colors (N, 3) float in [0, 1]).
    """
    import open3d as o3d

    from mvreg.viz import scan_colors

    idx = {s.name: i for i, s in enumerate(reg.scans)}
    colors = scan_colors(len(reg.scans)) / 255.0
    pts, cols = [], []
    for name, T in reg.T_world_scan.items():
        p = transform_points(T, reg.scans[idx[name]].points)
        pts.append(p)
        cols.append(np.repeat(colors[idx[name]][None], len(p), axis=0))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(pts)))
    pcd.colors = o3d.utility.Vector3dVector(np.concatenate(cols))
    v = voxel_size or reg.config.output.merged_voxel_size or reg.scales.fine_voxel
    pcd = pcd.voxel_down_sample(v)
    points = np.asarray(pcd.points)
    offset = reg.local_frame_offset
    return (points if offset is None else points + offset), np.asarray(pcd.colors)


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Binary little-endian PLY, float64 x y z, uchar colors; written atomically."""
    n = len(points)
    props = ["property double x", "property double y", "property double z"]
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors is not None:
        props += ["property uchar red", "property uchar green", "property uchar blue"]
        fields += [("r", "u1"), ("g", "u1"), ("b", "u1")]
    header = "\n".join(
        [
            "ply",
            "format binary_little_endian 1.0",
            "comment mvreg merged cloud",
            f"element vertex {n}",
        ]
        + props
        + ["end_header"]
    )
    rec = np.empty(n, dtype=fields)
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    if colors is not None:
        c = np.clip(np.round(colors * 255), 0, 255).astype(np.uint8)
        rec["r"], rec["g"], rec["b"] = c[:, 0], c[:, 1], c[:, 2]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write((header + "\n").encode("ascii"))
            f.write(rec.tobytes())


def _moved_after_certificate(reg) -> dict | None:
    j = getattr(reg, "joint_icp", None)
    if not j or not j.get("accepted"):
        return None
    return {
        "by": "joint point-to-plane ICP",
        "max_rotation_deg": j["max_rotation_change_deg"],
        "max_point_move": j["max_point_move"],
    }


def write_registration(reg, out: str | Path) -> dict[str, Path]:
    """Write every result file of ``reg`` into ``out`` (already prepared). Returns paths."""
    out = Path(out)
    T_world_scan = reg.T_world_scan_in_file_frame()  # the user's coordinates
    names = list(T_world_scan)
    poses = [T_world_scan[n] for n in names]
    paths = {
        "poses": out / "poses.json",
        "tum": out / "poses_tum.txt",
        "kitti": out / "poses_kitti.txt",
        "merged": out / "merged.ply",
        "report": out / "report.json",
    }
    cert = (
        reg.solve.certificate.to_dict() if reg.solve is not None and reg.solve.certificate else None
    )
    offset = reg.local_frame_offset
    write_poses_json(
        paths["poses"],
        T_world_scan,
        world_frame=names[0] if names else None,
        # Subtracted from every scan while registering; the poses are in the files' frame.
        local_frame_offset=None if offset is None else offset.tolist(),
        unregistered=reg.unregistered,
        # Left out: no independent evidence confirms the pose / a degree of freedom is free.
        unverified=list(getattr(reg, "unverified", [])),
        undetermined=list(getattr(reg, "undetermined", [])),
        certificate=cert,
        # The certificate is of the last global solve; the joint point-to-plane ICP after
        # it moved the poses by this much (None: it did not run or was not kept).
        moved_after_certificate=_moved_after_certificate(reg),
    )
    if poses:
        stamps = getattr(reg, "timestamps", None) or {}
        times = [stamps[n] for n in names] if all(n in stamps for n in names) else None
        write_poses_tum(paths["tum"], poses, timestamps=times)
        write_poses_kitti(paths["kitti"], poses)
        pts, cols = merged_cloud(reg)
        write_ply(paths["merged"], pts, cols)
        extra = write_merged(out / "merged", reg, reg.config.output.merged_format)
        if extra is not None:
            paths["merged_" + extra.suffix[1:]] = extra
    atomic_write_json(paths["report"], reg.report())
    return paths


def residual_heatmap(reg, max_points: int = 100_000, k: int = 12):
    """Merged points (P, 3) and each point's distance (P,) to the nearest point of another
    scan (inf when none within 4 feature voxels: no overlap there). The points are in the
    run's local frame (``reg.local_frame_offset`` not added: they go to the recording,
    which stores float32).

    One KD-tree over all scans (subsampled to ``max_points``), k nearest neighbours with a
    distance bound, the first one from another scan.
    """
    from scipy.spatial import cKDTree

    idx = {s.name: i for i, s in enumerate(reg.scans)}
    rng = np.random.default_rng(0)
    per = max(1, max_points // max(len(reg.T_world_scan), 1))
    pts, labels = [], []
    for label, (n, T) in enumerate(reg.T_world_scan.items()):
        p = reg.scans[idx[n]].points
        if len(p) > per:
            p = p[rng.choice(len(p), per, replace=False)]
        pts.append(transform_points(T, p))
        labels.append(np.full(len(p), label))
    pts = np.concatenate(pts)
    labels = np.concatenate(labels)
    dist, nn = cKDTree(pts).query(pts, k=k, distance_upper_bound=4.0 * reg.voxel_size)
    other = (nn < len(pts)) & (labels[np.minimum(nn, len(pts) - 1)] != labels[:, None])
    first = np.argmax(other, axis=1)
    res = np.where(other.any(axis=1), dist[np.arange(len(pts)), first], np.inf)
    return pts, res
