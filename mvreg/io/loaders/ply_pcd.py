"""PLY, PCD, XYZ / XYZN / XYZRGB and PTS scans, read through Open3D.

Open3D only logs a warning on a bad file and may return a partly filled cloud (a
truncated PLY gives the declared number of vertices, with garbage after the cut). So
PLY and PCD headers are parsed here first and the data size checked against what the
header declares; a short file raises :class:`~mvreg.errors.ScanFileError`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvreg.errors import ScanFileError
from mvreg.io.loaders.base import RawCloud

_PLY_TYPE_SIZES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1,
    "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4,
    "double": 8, "float64": 8,
}  # fmt: skip
_MAX_HEADER_BYTES = 1 << 20


def _read_header(path: Path, end_marker: bytes) -> tuple[list[str], bytes]:
    """Header lines (text) and the bytes after the header."""
    data = path.read_bytes()
    end = data.find(end_marker, 0, _MAX_HEADER_BYTES)
    if end < 0:
        raise ScanFileError(path, "corrupt header (no end of header found)")
    cut = data.find(b"\n", end + len(end_marker))
    cut = len(data) if cut < 0 else cut + 1
    header = data[:cut].decode("latin-1").splitlines()
    return header, data[cut:]


def _check_ply(path: Path) -> None:
    with path.open("rb") as f:
        magic = f.read(4)
    if magic[:3] != b"ply":
        raise ScanFileError(path, "not a PLY file (bad magic number)")
    header, body = _read_header(path, b"end_header")
    fmt = None
    elements: list[list] = []  # [name, count, fixed_size or None, num_props]
    for line in header:
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format" and len(tok) >= 2:
            fmt = tok[1]
        elif tok[0] == "element" and len(tok) >= 3:
            try:
                elements.append([tok[1], int(tok[2]), 0, 0])
            except ValueError:
                raise ScanFileError(path, f"corrupt PLY header line {line!r}") from None
        elif tok[0] == "property" and elements:
            el = elements[-1]
            el[3] += 1
            if tok[1] == "list":
                el[2] = None
            elif el[2] is not None:
                size = _PLY_TYPE_SIZES.get(tok[1])
                if size is None:
                    raise ScanFileError(path, f"unknown PLY property type {tok[1]!r}")
                el[2] += size
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ScanFileError(path, f"unknown PLY format {fmt!r}")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise ScanFileError(path, "PLY file has no vertex element")
    vi = names.index("vertex")
    num_vertices, vertex_size, vertex_props = elements[vi][1], elements[vi][2], elements[vi][3]
    if num_vertices <= 0:
        raise ScanFileError(path, "PLY header declares no vertices")
    before = elements[:vi]
    if fmt == "ascii":
        first = sum(e[1] for e in before)
        lines = body.split(b"\n", first + num_vertices)
        if len(lines) < first + num_vertices or (
            len(lines) == first + num_vertices and not lines[-1].strip()
        ):
            raise ScanFileError(
                path, f"truncated PLY: fewer data lines than the {num_vertices} vertices declared"
            )
        last = lines[first + num_vertices - 1].split()
        if vertex_size is not None and len(last) < vertex_props:
            raise ScanFileError(path, "truncated PLY: the last vertex line is incomplete")
    elif vertex_size is not None and all(e[2] is not None for e in before):
        need = sum(e[1] * e[2] for e in before) + num_vertices * vertex_size
        if len(body) < need:
            raise ScanFileError(
                path, f"truncated PLY: {len(body)} data bytes, the header declares {need}"
            )


def _check_pcd(path: Path) -> np.ndarray | None:
    """Checks a PCD file; returns the sensor origin if VIEWPOINT is not the default."""
    header, body = _read_header(path, b"\nDATA")
    fields: dict[str, list[str]] = {}
    for line in header:
        tok = line.split()
        if tok and not tok[0].startswith("#"):
            fields[tok[0].upper()] = tok[1:]
    try:
        num_points = int(fields.get("POINTS", fields.get("WIDTH", ["0"]))[0])
        sizes = [int(s) for s in fields.get("SIZE", [])]
        counts = [int(c) for c in fields.get("COUNT", ["1"] * len(sizes))]
    except ValueError:
        raise ScanFileError(path, "corrupt PCD header") from None
    if num_points <= 0:
        raise ScanFileError(path, "PCD header declares no points")
    data = fields.get("DATA", [""])[0].lower()
    if data == "binary" and sizes and len(counts) == len(sizes):
        need = num_points * sum(s * c for s, c in zip(sizes, counts, strict=True))
        if len(body) < need:
            raise ScanFileError(
                path, f"truncated PCD: {len(body)} data bytes, the header declares {need}"
            )
    elif data == "ascii" and body.count(b"\n") + (not body.endswith(b"\n")) < num_points:
        raise ScanFileError(path, f"truncated PCD: fewer lines than the {num_points} declared")
    vp = fields.get("VIEWPOINT")
    if vp is not None and len(vp) == 7:
        try:
            v = np.array([float(x) for x in vp])
        except ValueError:
            return None
        if not np.allclose(v, [0, 0, 0, 1, 0, 0, 0]):
            return v[:3]
    return None


class Open3DLoader:
    """PLY, PCD, XYZ, XYZN, XYZRGB and PTS through ``open3d.io.read_point_cloud``."""

    suffixes = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")

    def read(self, path: Path) -> RawCloud:
        import open3d as o3d

        suffix = path.suffix.lower()
        sensor_origin = None
        try:
            if suffix == ".ply":
                _check_ply(path)
            elif suffix == ".pcd":
                sensor_origin = _check_pcd(path)
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
