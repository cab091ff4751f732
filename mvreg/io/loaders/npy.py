"""NumPy ``.npy`` scans: an (N, 3) array of points or (N, 6) of points plus normals/colors.

In an (N, 6) array the last three columns are taken as normals when their rows have
unit length (to 1e-3 for 99% of rows), else as colors (divided by 255 when any value
exceeds 1).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvreg.errors import ScanFileError
from mvreg.io.loaders.base import RawCloud


class NpyLoader:
    suffixes = (".npy",)

    def count_points(self, path: Path) -> int:
        """Rows of the stored array (reads the header only)."""
        _check_magic(path)
        try:
            a = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError, EOFError) as e:
            raise ScanFileError(path, f"cannot read as a NumPy array ({e})") from e
        return int(a.shape[0]) if isinstance(a, np.ndarray) and a.ndim >= 1 else 0

    def read(self, path: Path) -> RawCloud:
        _check_magic(path)
        try:
            a = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as e:
            raise ScanFileError(path, f"cannot read as a NumPy array ({e})") from e
        if not isinstance(a, np.ndarray) or a.dtype.kind not in "fiu":
            kind = "complex numbers" if a.dtype.kind == "c" else f"dtype {a.dtype}"
            raise ScanFileError(path, f"expected real coordinates, the array holds {kind}")
        if a.ndim != 2 or a.shape[1] not in (3, 6):
            raise ScanFileError(path, f"expected an (N, 3) or (N, 6) array, got shape {a.shape}")
        a = a.astype(np.float64, copy=False)
        points = a[:, :3]
        if a.shape[1] == 3:
            return RawCloud(points)
        extra = a[:, 3:]
        with np.errstate(invalid="ignore"):
            unit = np.abs(np.linalg.norm(extra, axis=1) - 1.0) < 1e-3
        if unit.size and np.mean(unit) >= 0.99:
            return RawCloud(points, normals=extra)
        colors = extra / 255.0 if np.nanmax(extra, initial=0.0) > 1.0 else extra
        return RawCloud(points, colors=colors)


def _check_magic(path: Path) -> None:
    """ScanFileError unless the file starts with the .npy magic string (NumPy's own
    message for any other file speaks of pickled data)."""
    with path.open("rb") as f:
        head = f.read(6)
    if head != b"\x93NUMPY":
        raise ScanFileError(path, "not a .npy file (no NumPy header)")
