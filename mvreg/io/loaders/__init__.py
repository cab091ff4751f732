"""Scan loaders: one module per file format, found by suffix through a registry.

    scans = load_scans("scans/")            # every supported file, natural order
    scan = load_scan("scans/bun000.ply")    # one file -> Scan

Every file is checked (unreadable, empty, corrupt, all-NaN, duplicates only, too few
or more than ``max_points`` points, dangling symlink, symlink loop, file name not valid
UTF-8 -> ScanFileError naming the file, escaped); rows with NaN/inf coordinates are
dropped and counted in ``Scan.num_dropped_nonfinite``.

    listing = scan_folder("scans/")         # ScanListing(files, skipped)

Known sidecar files (``ground_truth.json``, ``ground_truth_tum.txt``, ``timestamps.txt``,
``synth.json``, ``README*``, ``*.md``, ``*.conf``, mvreg's own outputs) and hidden files
are ignored silently; any other file is returned in ``ScanListing.skipped`` with the reason, for the
caller to warn about and report.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

from mvreg.errors import InputError, ScanFileError
from mvreg.io.loaders.base import (
    DEFAULT_MAX_POINTS,
    DEFAULT_MIN_POINTS,
    RawCloud,
    Scan,
    ScanLoader,
    TooFewPointsError,
    validate_cloud,
)
from mvreg.io.loaders.e57 import E57Loader
from mvreg.io.loaders.las import LasLoader
from mvreg.io.loaders.listing import (
    ScanListing,
    check_file_entry,
    display_path,
    list_folder,
)
from mvreg.io.loaders.npy import NpyLoader
from mvreg.io.loaders.ply_pcd import Open3DLoader

__all__ = [
    "DEFAULT_MAX_POINTS",
    "DEFAULT_MIN_POINTS",
    "RawCloud",
    "Scan",
    "ScanListing",
    "ScanLoader",
    "TooFewPointsError",
    "display_path",
    "list_scan_files",
    "load_scan",
    "load_scan_file",
    "load_scans",
    "loader_for",
    "natural_key",
    "register_loader",
    "scan_folder",
    "supported_suffixes",
]

_REGISTRY: dict[str, ScanLoader] = {}


def register_loader(loader: ScanLoader) -> None:
    """Make ``loader`` the reader of each suffix in ``loader.suffixes`` (lower case, dot)."""
    if not isinstance(loader, ScanLoader):
        raise TypeError(f"{loader!r} does not implement the ScanLoader protocol")
    for suffix in loader.suffixes:
        _REGISTRY[suffix.lower()] = loader


for _loader in (Open3DLoader(), NpyLoader(), LasLoader(), E57Loader()):
    register_loader(_loader)


def supported_suffixes() -> list[str]:
    return sorted(_REGISTRY)


def loader_for(path: str | Path) -> ScanLoader:
    """The registered loader of ``path``'s suffix; InputError if none."""
    suffix = Path(path).suffix.lower()
    try:
        return _REGISTRY[suffix]
    except KeyError:
        raise ScanFileError(
            display_path(path),
            f"unsupported file type {suffix!r} (supported: {', '.join(supported_suffixes())})",
        ) from None


def natural_key(name: str) -> tuple:
    """Sort key putting ``scan_2`` before ``scan_10`` (case-insensitive)."""
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in parts)


def load_scan_file(
    path: str | Path,
    min_points: int = DEFAULT_MIN_POINTS,
    max_points: int | None = DEFAULT_MAX_POINTS,
    rejected: list[TooFewPointsError] | None = None,
) -> list[Scan]:
    """Read and check every scan of one file (one, or several for E57).

    Args:
        min_points: fewest valid, distinct points a scan must have.
        max_points: most points a scan may have (``max_points_per_scan``, default
            50 million); checked from the header or the file before reading it. None: no
            limit.
        rejected: when given, a scan with fewer than ``min_points`` valid points is
            appended to it (as :class:`TooFewPointsError`) and left out instead of raised.

    Raises:
        ScanFileError: missing, unreadable, empty, corrupt, all-NaN, duplicates only,
            fewer than ``min_points`` valid points or more than ``max_points`` points,
            dangling symlink, symlink loop or a file name that is not valid UTF-8.
    """
    path = Path(path)
    loader = loader_for(path)
    size = check_file_entry(path)
    if size == 0:
        raise ScanFileError(path, "empty file (0 bytes)")
    count = getattr(loader, "count_points", None)
    many = getattr(loader, "read_many", None)
    try:
        n = count(path) if max_points is not None and count is not None else 0
        if max_points is not None and n > max_points:
            raise ScanFileError(
                path,
                f"{n} points, more than the limit of {max_points} points per scan "
                "(max_points_per_scan; raise it if the machine has the memory)",
            )
        raws = many(path) if many is not None else [loader.read(path)]
    except ScanFileError:
        raise
    except OSError as e:
        raise ScanFileError(path, f"cannot read file ({e.strerror or e})") from e
    except Exception as e:  # noqa: BLE001 - whatever a format library raises: name the file
        raise ScanFileError(path, f"cannot read file ({type(e).__name__}: {e})") from e
    scans = []
    for raw in raws:
        try:
            scans.append(validate_cloud(path, raw, min_points=min_points))
        except TooFewPointsError as e:
            if rejected is None:
                raise
            rejected.append(e)
    return scans


def load_scan(
    path: str | Path,
    min_points: int = DEFAULT_MIN_POINTS,
    max_points: int | None = DEFAULT_MAX_POINTS,
) -> Scan:
    """Read and check a file holding one scan (see :func:`load_scan_file`).

    Raises:
        ScanFileError: as :func:`load_scan_file`, or the file holds several scans.
    """
    scans = load_scan_file(path, min_points=min_points, max_points=max_points)
    if len(scans) != 1:
        raise ScanFileError(
            path, f"holds {len(scans)} scans; load it with load_scans or load_scan_file"
        )
    return scans[0]


_SIDECAR_NAMES = {
    "ground_truth.json",
    "ground_truth_tum.txt",  # mvreg synth --sequence
    "timestamps.txt",
    "synth.json",
    "poses.json",
    "poses_tum.txt",
    "poses_kitti.txt",
    "report.json",
    "recording.rrd",
}
_SIDECAR_SUFFIXES = {".md", ".conf", ".rrd"}


def _is_sidecar(name: str) -> bool:
    low = name.lower()
    return (
        low in _SIDECAR_NAMES
        or Path(low).suffix in _SIDECAR_SUFFIXES
        or low.startswith("readme")
        or low.startswith(".")
    )


def scan_folder(folder: str | Path) -> ScanListing:
    """The scan files of ``folder`` in natural order, and the other files skipped.

    Hidden files and known sidecar files are ignored silently; every other entry that is
    not a scan file of a supported suffix is in ``skipped`` with the reason.

    Raises:
        InputError: ``folder`` is not a directory or holds no scan file.
        ScanFileError: a scan file (supported suffix) is a dangling symlink, a symlink
            loop, not a regular file, or its name is not valid UTF-8.
    """
    listing = list_folder(Path(folder), set(_REGISTRY), _is_sidecar)
    if not listing.files:
        raise InputError(
            f"{display_path(folder)}: no scan files found "
            f"(supported: {', '.join(supported_suffixes())})"
        )
    listing.files.sort(key=lambda p: natural_key(p.name))
    return listing


def list_scan_files(folder: str | Path) -> list[Path]:
    """Scan files of ``folder`` in natural sort order (see :func:`scan_folder`)."""
    return scan_folder(folder).files


def load_scans(
    source: str | Path | Iterable[str | Path],
    min_points: int = DEFAULT_MIN_POINTS,
    max_points: int | None = DEFAULT_MAX_POINTS,
) -> list[Scan]:
    """Load every scan of a folder (or an explicit list of files), in natural order
    (the scans of a multi-scan E57 file in the file's order)."""
    if isinstance(source, (str, Path)):
        paths = list_scan_files(source)
    else:
        paths = [Path(p) for p in source]
        if not paths:
            raise InputError("no scan files given")
    return [
        scan
        for p in paths
        for scan in load_scan_file(p, min_points=min_points, max_points=max_points)
    ]
