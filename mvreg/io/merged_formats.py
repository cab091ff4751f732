"""The registered scans as one file that keeps them apart: LAZ or E57 (``output.merged_format``).

``merged.ply`` is a voxel-downsampled preview of the union. These formats hold every point
of every registered scan, one scan per input with its pose, as the tools that read them
expect:

* **LAZ** (``merged.laz``, LAS 1.4, point format 6, or 7 when the scans have colors):
  every point in the world frame of ``poses.json`` (the files' frame: a georeferenced
  input keeps its coordinates), ``point_source_id`` = the scan's index in ``poses.json``
  (so at most 65,535 scans), and a JSON VLR (user id ``mvreg``, record id 1) that lists
  the scans in that order with their ``T_world_scan``. The scale is a power of ten at most
  a hundredth of the fine voxel, coarser only when the extent would not fit 32-bit
  integers.
* **E57** (``merged.e57``): one data3D scan per registered input, named after it, its
  points in its own scanner frame and its pose (``T_world_scan``, files' frame) in the
  scan header, which is how E57 stores registered scans. pye57 writes coordinates in
  single precision; where that would round them by more than a hundredth of the fine
  voxel (georeferenced coordinates), a scan's points are stored shifted by their rounded
  centroid and its pose takes the shift (the world points are the same).

Both are written atomically (a temporary file, then a rename), like every output.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mvreg.geometry import transform_points
from mvreg.io.atomic import OutputWriteError, atomic_path

FORMATS = ("ply", "laz", "e57")
VLR_USER_ID = "mvreg"
VLR_RECORD_ID = 1


class MergedFormatError(OutputWriteError):
    """The registered scans cannot be written in the requested format (exit code 4)."""


def _registered(reg):
    """[(name, T_world_scan in the files' frame, scan)] in the order of poses.json."""
    by_name = {s.name: s for s in reg.scans}
    T = reg.T_world_scan_in_file_frame()
    offset = reg.local_frame_offset
    out = []
    for name, T_fw in T.items():
        scan = by_name[name]
        # Scans are held shifted by the local frame offset: back to the file's points.
        pts = scan.points if offset is None else scan.points + offset
        out.append((name, T_fw, pts, scan.colors))
    return out


def _las_scale(lo: np.ndarray, hi: np.ndarray, fine_voxel: float) -> float:
    scale = 10.0 ** np.floor(np.log10(max(fine_voxel / 100.0, 1e-12)))
    while np.max(hi - lo) / scale >= 2.0**31 - 1:
        scale *= 10.0
    return float(scale)


def write_merged_laz(path: Path, reg) -> None:
    """Every point of every registered scan in the world frame, one source id per scan."""
    import laspy

    scans = _registered(reg)
    if len(scans) > 65535:
        raise MergedFormatError(path, f"LAZ holds at most 65535 scans, not {len(scans)}")
    world = [transform_points(T, p) for _, T, p, _ in scans]
    pts = np.concatenate(world) if world else np.zeros((0, 3))
    colored = bool(scans) and all(c is not None for *_, c in scans)
    header = laspy.LasHeader(point_format=7 if colored else 6, version="1.4")
    lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (np.zeros(3), np.ones(3))
    header.offsets = np.floor(lo)
    header.scales = np.full(3, _las_scale(lo, hi, reg.scales.fine_voxel))
    record = [{"name": name, "T_world_scan": np.asarray(T).tolist()} for name, T, *_ in scans]
    header.vlrs.append(
        laspy.VLR(
            user_id=VLR_USER_ID, record_id=VLR_RECORD_ID, description="mvreg scans and poses",
            record_data=json.dumps({"format": "mvreg.laz_scans/1", "scans": record}).encode(),
        )
    )  # fmt: skip
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.point_source_id = np.concatenate(
        [np.full(len(p), k, np.uint16) for k, p in enumerate(world)] or [np.zeros(0, np.uint16)]
    )
    if colored:
        rgb = np.concatenate([np.clip(np.round(c * 65535), 0, 65535) for *_, c in scans])
        las.red, las.green, las.blue = (rgb[:, k].astype(np.uint16) for k in range(3))
    with atomic_path(path) as tmp:
        las.write(str(tmp), do_compress=True)


def fit_single_precision(T, pts, fine_voxel):
    """pye57 stores coordinates as float32: when that would round them by more than a
    hundredth of the fine voxel (georeferenced coordinates), the points are stored shifted
    by their rounded centroid and the shift folded into the pose (same world points)."""
    if len(pts) == 0 or np.max(np.abs(pts)) * 2.0**-24 <= fine_voxel / 100:
        return T, pts
    c = np.round(pts.mean(axis=0))
    shift = np.eye(4)
    shift[:3, 3] = c
    return T @ shift, pts - c


def write_merged_e57(path: Path, reg) -> None:
    """One E57 data3D per registered scan: its own points and its pose."""
    import pye57
    from scipy.spatial.transform import Rotation

    with atomic_path(path) as tmp:
        e57 = pye57.E57(str(tmp), mode="w")
        try:
            for name, T, pts, colors in _registered(reg):
                T, pts = fit_single_precision(T, pts, reg.scales.fine_voxel)
                data = {
                    "cartesianX": np.ascontiguousarray(pts[:, 0], np.float64),
                    "cartesianY": np.ascontiguousarray(pts[:, 1], np.float64),
                    "cartesianZ": np.ascontiguousarray(pts[:, 2], np.float64),
                }
                if colors is not None:
                    c = np.clip(np.round(colors * 255), 0, 255).astype(np.uint8)
                    data.update(colorRed=c[:, 0].copy(), colorGreen=c[:, 1].copy(),
                                colorBlue=c[:, 2].copy())  # fmt: skip
                x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
                e57.write_scan_raw(
                    data, name=name, rotation=np.array([w, x, y, z]), translation=T[:3, 3]
                )
        finally:
            e57.close()


def write_merged(path_stem: Path, reg, fmt: str) -> Path | None:
    """Write the registered scans as ``path_stem`` + ``.laz`` / ``.e57``; None for ply
    (``merged.ply`` is always written). Raises :class:`MergedFormatError`."""
    if fmt == "ply":
        return None
    path = path_stem.with_suffix("." + fmt)
    if fmt not in FORMATS:
        raise MergedFormatError(path, f"merged_format {fmt!r} is not one of {', '.join(FORMATS)}")
    (write_merged_laz if fmt == "laz" else write_merged_e57)(path, reg)
    return path
