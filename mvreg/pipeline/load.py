"""The load stage: scans from a folder (checked, natural order) or from point arrays.

Returns the scans, the source as text and the ground truth (``ground_truth.json`` in the
folder, used only to evaluate). Raises InputError / ScanFileError naming the culprit.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mvreg.errors import InputError, ScanFileError
from mvreg.io.loaders import Scan, load_scan_file, scan_folder
from mvreg.io.poses import read_poses_json


@dataclass
class Loaded:
    """What the load stage read: the scans (in order), the source as text (None for
    arrays), the ground truth ({name: (4, 4)}, evaluation only) and the folder entries
    that were not scans (``[{"file", "reason"}]``: the CLI warns about them)."""

    scans: list[Scan]
    source: str | None
    truth: dict | None
    skipped: list[dict] = field(default_factory=list)


def load_source(
    source, names, min_points: int, max_points: int | None, truth, prog, what="registration"
) -> Loaded:
    """Scans from a folder (every scan of every supported file, natural order) or from
    (N, 3) arrays, checked; raises InputError / ScanFileError naming the culprit."""
    if isinstance(source, (str, Path)):
        out = _load_folder(Path(source), min_points, max_points, truth, prog)
    else:
        out = Loaded(_from_arrays(source, names, min_points), None, truth)
    out.scans = [drop_far_strays(s, min_points) for s in out.scans]
    if len(out.scans) < 2:
        raise InputError(f"{source}: {what} needs at least 2 scans, found {len(out.scans)}")
    return out


# A point this many times further from its scan's median point than the scan's median
# distance from it is a stray (a glitch at 1e9): no scan spans four orders of magnitude.
FAR_STRAY_FACTOR = 1e4


def drop_far_strays(scan: Scan, min_points: int) -> Scan:
    """``scan`` without points further than ``FAR_STRAY_FACTOR`` times its median radius
    from its median point (counted in ``num_dropped_far``); the same object when none is.
    One such point otherwise makes the voxel grids of every later stage impossibly large."""
    centre = np.median(scan.points, axis=0)
    r = np.linalg.norm(scan.points - centre, axis=1)
    radius = float(np.median(r))
    far = r > FAR_STRAY_FACTOR * max(radius, np.finfo(float).tiny)
    if not np.any(far):
        return scan
    keep = ~far
    if keep.sum() < min_points:
        raise ScanFileError(scan.path, f"only {int(keep.sum())} points away from far strays")
    return replace(
        scan,
        points=scan.points[keep],
        normals=None if scan.normals is None else scan.normals[keep],
        colors=None if scan.colors is None else scan.colors[keep],
        num_dropped_far=int(far.sum()),
    )


def _load_folder(folder: Path, min_points, max_points, truth, prog) -> Loaded:
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder of scans")
    listing = scan_folder(folder)
    if not listing.files:
        raise InputError(f"{folder}: no scan files found")
    prog.stage("load", len(listing.files))
    scans = []
    for f in listing.files:
        scans += load_scan_file(f, min_points=min_points, max_points=max_points)
        prog.advance()
    if truth is None and (folder / "ground_truth.json").exists():
        truth = read_poses_json(folder / "ground_truth.json")
    return Loaded(scans, str(folder), truth, listing.skipped_report())


def _from_arrays(source, names, min_points: int) -> list[Scan]:
    arrays = list(source)
    names = list(names) if names is not None else [f"scan_{i:03d}" for i in range(len(arrays))]
    if len(names) != len(arrays):
        raise InputError(f"{len(names)} names for {len(arrays)} point arrays")
    scans = []
    for n, a in zip(names, arrays, strict=True):
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(f"{n}: points must be an (N, 3) array, got {a.shape}")
        ok = np.all(np.isfinite(a), axis=1)
        if ok.sum() < min_points:
            raise InputError(f"{n}: {int(ok.sum())} valid points, need {min_points}")
        scans.append(
            Scan(name=n, path=Path(n), points=a[ok], num_dropped_nonfinite=int((~ok).sum()))
        )
    return scans
