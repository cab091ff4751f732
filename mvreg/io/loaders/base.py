"""The scan record every loader produces, the loader contract, and the common checks."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from mvreg.errors import ScanFileError

#: Default minimum number of valid points a scan must have.
DEFAULT_MIN_POINTS = 100
#: Default largest number of points a scan may have (``max_points_per_scan``): about
#: 1.2 GB of float64 coordinates, and several times that while registering.
DEFAULT_MAX_POINTS = 50_000_000


@dataclass
class RawCloud:
    """What a format module returns before validation (arrays as read, maybe with NaN)."""

    points: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    sensor_origin: np.ndarray | None = None
    name: str | None = None  # default: the file name (several scans per file: set it)
    pose_hint: np.ndarray | None = None  # stored (4, 4) scanner-to-world pose, if any


@dataclass
class Scan:
    """One scan as loaded from disk, in its own (local) frame and the file's units.

    Attributes:
        name: file name (e.g. ``"bun000.ply"``), unique within a folder.
        path: where it was read from.
        points: (N, 3) float64, all finite.
        normals: (N, 3) float64 or None (as stored in the file; not re-oriented).
        colors: (N, 3) float64 in [0, 1] or None.
        num_dropped_nonfinite: rows removed because a coordinate was NaN or inf.
        sensor_origin: (3,) float64 sensor position in the scan frame when the file
            records one (PCD ``VIEWPOINT`` other than the default), else None.
        T_world_scan_hint: (4, 4) float64 scan-to-world pose stored in the file (E57
            scanner poses), a possible initial guess; None when the file has none.
        num_dropped_far: points dropped by the load stage as far strays
            (:func:`mvreg.pipeline.load.drop_far_strays`).
        local_frame_offset: (3,) float64 subtracted from the file's coordinates by the
            load stage (georeferenced folders, :func:`mvreg.pipeline.load.to_local_frame`):
            the file holds ``points + local_frame_offset``. None: the file's own coordinates.
    """

    name: str
    path: Path
    points: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    num_dropped_nonfinite: int = 0
    sensor_origin: np.ndarray | None = field(default=None)
    T_world_scan_hint: np.ndarray | None = field(default=None, repr=False)
    num_dropped_far: int = 0
    local_frame_offset: np.ndarray | None = field(default=None, repr=False)

    @property
    def num_points(self) -> int:
        return int(self.points.shape[0])

    def __repr__(self) -> str:
        extras = [k for k in ("normals", "colors") if getattr(self, k) is not None]
        dropped = f", dropped_nonfinite={self.num_dropped_nonfinite}" * bool(
            self.num_dropped_nonfinite
        )
        with_ = f", with {'+'.join(extras)}" if extras else ""
        return f"Scan({self.name!r}, points={self.num_points}{with_}{dropped})"


class TooFewPointsError(ScanFileError):
    """A scan has fewer than ``min_points`` usable points. The load stage of ``register``
    lists such a scan as unregistered (with ``reason``) and goes on with the others.

    Attributes:
        scan: the scan's name (the file name, or the scan's name inside an E57 file).
    """

    def __init__(self, path, reason: str, scan: str | None = None):
        self.scan = scan or Path(path).name
        super().__init__(path, reason)

    def __reduce__(self):
        return (type(self), (self.path, self.reason, self.scan))


@runtime_checkable
class ScanLoader(Protocol):
    """Reads one file format. Registered by suffix in :mod:`mvreg.io.loaders`.

    ``read`` raises :class:`~mvreg.errors.ScanFileError` for files it cannot parse and
    returns the arrays as stored; the common checks (NaN rows, minimum size) are done by
    :func:`mvreg.io.loaders.load_scan`, not by each loader.
    """

    suffixes: tuple[str, ...]

    def read(self, path: Path) -> RawCloud: ...


def _optional_rows(path: Path, a: np.ndarray | None, n: int, what: str) -> np.ndarray | None:
    if a is None:
        return None
    a = np.asarray(a, dtype=np.float64)
    if a.size == 0:
        return None
    if a.shape != (n, 3):
        raise ScanFileError(path, f"{what} have shape {a.shape}, expected ({n}, 3)")
    return a


def _pose_hint(t) -> np.ndarray | None:
    """A stored pose as (4, 4) float64 when it is finite and rigid, else None."""
    if t is None:
        return None
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        return None
    r = t[:3, :3]
    if np.max(np.abs(r.T @ r - np.eye(3))) > 1e-6 or np.linalg.det(r) < 0:
        return None
    return t


def count_distinct(points: np.ndarray) -> int:
    """Number of distinct rows of an (N, 3) float64 array."""
    rows = np.ascontiguousarray(points).view(np.dtype((np.void, points.dtype.itemsize * 3)))
    return int(np.unique(rows.ravel()).shape[0])


def _check_distinct(path: Path, pts: np.ndarray, min_points: int) -> None:
    """Refuse a scan with fewer than ``min_points`` distinct points (duplicates only)."""
    head = pts[: 4 * max(min_points, 1)]
    if count_distinct(head) >= min_points:
        return  # the common case, decided on a few rows
    k = count_distinct(pts)
    if k < min_points:
        raise ScanFileError(
            path,
            f"{len(pts)} points but only {k} distinct; need min_points = {min_points} "
            "distinct points",
        )


def validate_cloud(path: Path, raw: RawCloud, min_points: int = DEFAULT_MIN_POINTS) -> Scan:
    """Common checks of every loaded file -> :class:`Scan`.

    Rows with a NaN/inf coordinate are dropped and counted; non-finite normals or colors
    (on finite points) make the scan carry none. Raises ScanFileError when nothing
    usable is left or fewer than ``min_points`` points remain.
    """
    path = Path(path)
    pts = np.asarray(raw.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ScanFileError(path, f"points have shape {pts.shape}, expected (N, 3)")
    n = pts.shape[0]
    if n == 0:
        raise ScanFileError(path, "no points could be read (empty or unreadable file)")
    normals = _optional_rows(path, raw.normals, n, "normals")
    colors = _optional_rows(path, raw.colors, n, "colors")
    finite = np.all(np.isfinite(pts), axis=1)
    num_valid = int(finite.sum())
    if num_valid == 0:
        raise ScanFileError(path, f"all {n} points have NaN or infinite coordinates")
    if num_valid < min_points:
        raise TooFewPointsError(
            path,
            f"only {num_valid} valid points, fewer than the minimum of {min_points} (min_points)",
            scan=raw.name or path.name,
        )
    if num_valid < n:
        pts = pts[finite]
        normals = None if normals is None else normals[finite]
        colors = None if colors is None else colors[finite]
    if normals is not None and not np.all(np.isfinite(normals)):
        normals = None
    if colors is not None and not np.all(np.isfinite(colors)):
        colors = None
    _check_distinct(path, pts, min_points)
    origin = None
    if raw.sensor_origin is not None:
        origin = np.asarray(raw.sensor_origin, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(origin)):
            origin = None
    return Scan(
        name=raw.name or path.name,
        path=path,
        points=np.ascontiguousarray(pts),
        normals=normals,
        colors=colors,
        num_dropped_nonfinite=n - num_valid,
        sensor_origin=origin,
        T_world_scan_hint=_pose_hint(raw.pose_hint),
    )
