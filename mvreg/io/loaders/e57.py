"""E57 scans (ASTM E2807) through ``pye57``: one file may hold several scans.

Each scan of the file becomes one :class:`~mvreg.io.loaders.base.Scan` in its own
(scanner) frame: named after the file when it holds one scan, else ``file.e57#k``
(k = 0, 1, ... in the file's order). The pose the file stores for a scan (scanner to
world) is kept as ``Scan.T_world_scan_hint`` (a 4x4 array, None when the file has none),
for use as an initial guess. Spherical coordinates are converted to Cartesian; colors are
divided by their stored maximum (255 or 65535).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvreg.errors import ScanFileError
from mvreg.io.loaders.base import RawCloud


def _open(path: Path):
    try:
        import pye57
    except ImportError:  # pragma: no cover - pye57 is a dependency
        raise ScanFileError(path, "E57 support needs: pip install pye57") from None
    try:
        return pye57.E57(str(path))
    except Exception as e:  # noqa: BLE001 - libE57 raises its own exception types
        raise ScanFileError(path, f"not a readable E57 file ({_first_line(e)})") from e


def _first_line(e: Exception) -> str:
    """libE57's message without the debug dump it appends on further lines."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return lines[0].rstrip("(").strip() if lines else type(e).__name__


def _points(data: dict) -> np.ndarray:
    if "cartesianX" in data:
        return np.column_stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]])
    from pye57.utils import convert_spherical_to_cartesian

    rae = np.column_stack(
        [data["sphericalRange"], data["sphericalAzimuth"], data["sphericalElevation"]]
    )
    return convert_spherical_to_cartesian(rae)


def _hint(header) -> np.ndarray | None:
    if not header.has_pose():
        return None
    t = np.eye(4)
    t[:3, :3] = header.rotation_matrix
    t[:3, 3] = header.translation
    return t


def _one_scan(path: Path, e57, k: int, name: str) -> RawCloud:
    try:
        data = e57.read_scan(k, colors=True, transform=False, ignore_missing_fields=True)
        header = e57.get_header(k)
        hint = _hint(header)
    except Exception as e:  # noqa: BLE001 - libE57 raises its own exception types
        raise ScanFileError(path, f"scan {k} is not readable ({_first_line(e)})") from e
    colors = None
    if all(c in data for c in ("colorRed", "colorGreen", "colorBlue")):
        rgb = np.column_stack([data["colorRed"], data["colorGreen"], data["colorBlue"]])
        rgb = rgb.astype(np.float64)
        colors = rgb / (255.0 if rgb.size and rgb.max() <= 255 else 65535.0)
    return RawCloud(np.asarray(_points(data), np.float64), colors=colors, name=name, pose_hint=hint)


class E57Loader:
    """``.e57`` files, one or several scans each."""

    suffixes = (".e57",)

    def count_points(self, path: Path) -> int:
        """Points of the largest scan of the file (the limit is per scan)."""
        e57 = _open(path)
        try:
            return max((e57.get_header(k).point_count for k in range(e57.scan_count)), default=0)
        finally:
            e57.close()

    def read_many(self, path: Path) -> list[RawCloud]:
        e57 = _open(path)
        try:
            n = e57.scan_count
            if n == 0:
                raise ScanFileError(path, "the E57 file holds no scans")
            names = [path.name] if n == 1 else [f"{path.name}#{k}" for k in range(n)]
            return [_one_scan(path, e57, k, names[k]) for k in range(n)]
        finally:
            e57.close()

    def read(self, path: Path) -> RawCloud:
        clouds = self.read_many(path)
        if len(clouds) != 1:
            raise ScanFileError(
                path, f"holds {len(clouds)} scans; load it with load_scans or load_scan_file"
            )
        return clouds[0]
