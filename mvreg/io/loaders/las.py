"""LAS and LAZ scans (ASPRS point clouds) through ``laspy`` (LAZ with the ``lazrs`` backend).

Coordinates are the scaled, offset float64 values ``x, y, z`` as stored (georeferenced
files keep their large offsets; the pipeline shifts them into a local frame). Colors,
when the point format has them, are divided by 65535 (or by 255 when no value exceeds
255, as some writers store 8-bit colors).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from mvreg.errors import ScanFileError
from mvreg.io.loaders.base import RawCloud

_MIN_HEADER = 227
_VLR_HEADER = 54


def check_las_header(path: Path) -> int:
    """Check the public header block against the file size; the number of points.

    Done before laspy reads the file: laspy trusts the header's sizes and may try to
    allocate gigabytes for a corrupt one.
    """
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(375)
    if head[:4] != b"LASF":
        raise ScanFileError(path, "not a LAS/LAZ file (bad signature)")
    if len(head) < _MIN_HEADER:
        raise ScanFileError(path, f"truncated LAS header ({len(head)} bytes)")
    major, minor = head[24], head[25]
    header_size, offset, num_vlrs = struct.unpack_from("<HII", head, 94)
    fmt, record, count = struct.unpack_from("<BHI", head, 104)
    if major != 1 or minor > 4:
        raise ScanFileError(path, f"unsupported LAS version {major}.{minor}")
    if minor >= 4 and len(head) >= 255 and count == 0:
        count = struct.unpack_from("<Q", head, 247)[0]
    if not _MIN_HEADER <= header_size <= offset <= size:
        raise ScanFileError(
            path,
            f"corrupt LAS header (header size {header_size}, point data at byte {offset}, "
            f"file size {size})",
        )
    if num_vlrs * _VLR_HEADER > offset - header_size:
        raise ScanFileError(path, f"corrupt LAS header ({num_vlrs} VLRs do not fit)")
    compressed = bool(fmt & 0x80) or path.suffix.lower() == ".laz"
    if not compressed and offset + count * record > size:
        held = (size - offset) // max(record, 1)
        raise ScanFileError(
            path, f"truncated LAS: the header declares {count} points, the file holds {held}"
        )
    return int(count)


def _laspy():
    try:
        import laspy
    except ImportError:  # pragma: no cover - laspy is a dependency
        raise ScanFileError("laspy", "LAS/LAZ support needs: pip install laspy lazrs") from None
    return laspy


class LasLoader:
    """``.las`` and ``.laz`` files."""

    suffixes = (".las", ".laz")

    def count_points(self, path: Path) -> int:
        return check_las_header(path)

    def read(self, path: Path) -> RawCloud:
        check_las_header(path)
        laspy = _laspy()
        try:
            las = laspy.read(path)
        except (laspy.errors.LaspyException, ValueError, OSError, EOFError) as e:
            raise ScanFileError(path, f"not a readable LAS/LAZ file ({e})") from e
        points = np.column_stack(
            [np.asarray(las.x, np.float64), np.asarray(las.y, np.float64), las.z]
        ).astype(np.float64)
        colors = None
        names = set(las.point_format.dimension_names)
        if {"red", "green", "blue"} <= names:
            rgb = np.column_stack([las.red, las.green, las.blue]).astype(np.float64)
            colors = rgb / (255.0 if rgb.size and rgb.max() <= 255 else 65535.0)
        return RawCloud(points, colors=colors)
