"""Scan loaders: one module per file format, found by suffix through a registry.

    scans = load_scans("scans/")            # every supported file, natural order
    scan = load_scan("scans/bun000.ply")    # one file -> Scan

Every file is checked (unreadable, empty, all-NaN, too few points -> ScanFileError
naming the file); rows with NaN/inf coordinates are dropped and counted in
``Scan.num_dropped_nonfinite``. Other files in the folder (``ground_truth.json``,
``timestamps.txt``, ...) are ignored.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

from mvreg.errors import InputError, ScanFileError
from mvreg.io.loaders.base import DEFAULT_MIN_POINTS, RawCloud, Scan, ScanLoader, validate_cloud
from mvreg.io.loaders.npy import NpyLoader
from mvreg.io.loaders.ply_pcd import Open3DLoader

__all__ = [
    "DEFAULT_MIN_POINTS",
    "RawCloud",
    "Scan",
    "ScanLoader",
    "list_scan_files",
    "load_scan",
    "load_scans",
    "loader_for",
    "natural_key",
    "register_loader",
    "supported_suffixes",
]

_REGISTRY: dict[str, ScanLoader] = {}


def register_loader(loader: ScanLoader) -> None:
    """Make ``loader`` the reader of each suffix in ``loader.suffixes`` (lower case, dot)."""
    if not isinstance(loader, ScanLoader):
        raise TypeError(f"{loader!r} does not implement the ScanLoader protocol")
    for suffix in loader.suffixes:
        _REGISTRY[suffix.lower()] = loader


for _loader in (Open3DLoader(), NpyLoader()):
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
            path, f"unsupported file type {suffix!r} (supported: {', '.join(supported_suffixes())})"
        ) from None


def natural_key(name: str) -> tuple:
    """Sort key putting ``scan_2`` before ``scan_10`` (case-insensitive)."""
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in parts)


def load_scan(path: str | Path, min_points: int = DEFAULT_MIN_POINTS) -> Scan:
    """Read and check one scan file.

    Raises:
        ScanFileError: missing, unreadable, empty, corrupt, all-NaN, or fewer than
            ``min_points`` valid points.
    """
    path = Path(path)
    loader = loader_for(path)
    if not path.is_file():
        raise ScanFileError(path, "no such file")
    try:
        size = path.stat().st_size
    except OSError as e:
        raise ScanFileError(path, f"cannot read file ({e.strerror or e})") from e
    if size == 0:
        raise ScanFileError(path, "empty file (0 bytes)")
    return validate_cloud(path, loader.read(path), min_points=min_points)


def list_scan_files(folder: str | Path) -> list[Path]:
    """Scan files of ``folder`` (supported suffixes, not hidden) in natural sort order.

    Raises:
        InputError: ``folder`` is not a directory or holds no scan file.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    files = [
        p
        for p in folder.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in _REGISTRY
    ]
    if not files:
        raise InputError(
            f"{folder}: no scan files found (supported: {', '.join(supported_suffixes())})"
        )
    return sorted(files, key=lambda p: natural_key(p.name))


def load_scans(
    source: str | Path | Iterable[str | Path], min_points: int = DEFAULT_MIN_POINTS
) -> list[Scan]:
    """Load every scan of a folder (or an explicit list of files), in natural order."""
    if isinstance(source, (str, Path)):
        paths = list_scan_files(source)
    else:
        paths = [Path(p) for p in source]
        if not paths:
            raise InputError("no scan files given")
    return [load_scan(p, min_points=min_points) for p in paths]
