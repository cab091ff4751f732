"""PLY, PCD, XYZ / XYZN / XYZRGB and PTS scans, read through Open3D.

Open3D only logs a warning on a bad file and may return a partly filled cloud, so PLY
and PCD files are first checked against their headers, and text files (XYZ, PTS) line by
line, by :mod:`mvreg.io.loaders.checks` (streaming; a short, long or corrupt file, a value
that is not a number or overflows, raises :class:`~mvreg.errors.ScanFileError` naming the
file and the line).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvreg.errors import ScanFileError
from mvreg.io.loaders.base import RawCloud
from mvreg.io.loaders.checks import (
    check_pcd,
    check_ply,
    check_text,
    count_lines,
    declared_points,
    read_pcd_doubles,
    read_ply_vertices,
)


class Open3DLoader:
    """PCD through ``open3d.io.read_point_cloud``; PLY, XYZ, XYZN, XYZRGB, PTS and binary
    PCD with 8-byte coordinates, once checked, through NumPy."""

    suffixes = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")

    def count_points(self, path: Path) -> int:
        """Points the file declares (PLY/PCD header) or may hold (text lines)."""
        if path.suffix.lower() in (".ply", ".pcd"):
            return declared_points(path)
        return count_lines(path)

    def read(self, path: Path) -> RawCloud:
        import open3d as o3d

        suffix = path.suffix.lower()
        sensor_origin = None
        try:
            if suffix == ".ply":  # NumPy: Open3D misreads other property orders, and
                check_ply(path)  # aborts on a header line of ~1 KB
                return RawCloud(*read_ply_vertices(path))
            if suffix == ".pcd":
                sensor_origin = check_pcd(path)
                doubles = read_pcd_doubles(path)
                if doubles is not None:
                    return RawCloud(*doubles, sensor_origin=sensor_origin)
            else:  # NumPy: Open3D misreads PTS rows of 7 values (x y z i r g b)
                check_text(path, 3 if suffix in (".xyz", ".pts") else 6, suffix == ".pts")
                return _read_text(path, suffix)
        except OSError as e:
            raise ScanFileError(path, f"cannot read file ({e.strerror or e})") from e
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            pcd = o3d.io.read_point_cloud(
                str(path), format="auto", remove_nan_points=False, remove_infinite_points=False
            )
        points = np.asarray(pcd.points, dtype=np.float64)
        normals = np.asarray(pcd.normals, dtype=np.float64) if pcd.has_normals() else None
        colors = np.asarray(pcd.colors, dtype=np.float64) if pcd.has_colors() else None
        return RawCloud(points, normals, colors, sensor_origin)


def _read_text(path: Path, suffix: str) -> RawCloud:
    """A checked XYZ / XYZN / XYZRGB / PTS file: x y z, then normals (XYZN), colors
    (XYZRGB; PTS rows of 6 values: r g b, of 7: intensity r g b), 0-255 scaled to [0, 1]."""
    rows = np.loadtxt(path, skiprows=1 if suffix == ".pts" else 0, ndmin=2, dtype=np.float64)
    extra = {
        ".xyzn": ("normals", 3),
        ".xyzrgb": ("colors", 3),
        ".pts": ("colors", {6: 3, 7: 4}.get(rows.shape[1])),
    }.get(suffix)
    out = {}
    if extra is not None and extra[1] is not None:
        cols = rows[:, extra[1] : extra[1] + 3]
        if extra[0] == "colors" and cols.max(initial=0.0) > 1.0:
            cols = cols / 255.0
        out[extra[0]] = cols
    return RawCloud(rows[:, :3], **out)
