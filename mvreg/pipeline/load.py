"""The load stage: scans from a folder (checked, natural order) or from point arrays.

Returns the scans, the source as text and the ground truth (``ground_truth.json`` in the
folder, used only to evaluate). Raises InputError / ScanFileError naming the culprit.

A scan of a folder with fewer than ``min_points`` points is left out and reported (it is
listed as unregistered), unless fewer than 2 scans remain. Scans far from their
coordinate origin (georeferenced: UTM, ~1e6 m) are shifted into a local frame by one
offset for the whole input (:func:`to_local_frame`), in float64 before any other stage:
later stages lose digits far from the origin (a normal's covariance subtracts squares of
~1e12 there; the recording is float32).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mvreg.errors import InputError, ScanFileError
from mvreg.io.loaders import Scan, TooFewPointsError, display_path, load_scan_file, scan_folder
from mvreg.io.poses import pose_with_offset, read_poses_json

LOAD_THREADS = 2
"""Files read at a time (at most this many whole scans in memory beyond those kept)."""


@dataclass
class Loaded:
    """What the load stage read: the scans (in order), the source as text (None for
    arrays), the ground truth ({name: (4, 4)}, evaluation only), the folder entries that
    were not read (``[{"file", "reason"}]``: the CLI warns about them) and the scans left
    out for too few points (same list, with a ``"scan"`` key: reported as unregistered by
    :class:`~mvreg.pipeline.result.Registration`). ``local_frame_offset``: (3,) float64
    subtracted from every scan and from the truth (None: none)."""

    scans: list[Scan]
    source: str | None
    truth: dict | None
    skipped: list[dict] = field(default_factory=list)
    local_frame_offset: np.ndarray | None = None


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
        left_out = [s["scan"] for s in out.skipped if "scan" in s]
        extra = (
            f" ({len(left_out)} more with fewer than min_points = {min_points} points: "
            f"{', '.join(left_out[:8])}{', ...' if len(left_out) > 8 else ''})"
        )
        raise InputError(
            f"{source}: {what} needs at least 2 scans, found {len(out.scans)}"
            + (extra if left_out else "")
        )
    return to_local_frame(out)


# The scans of an input whose box is further from the coordinate origin than this many
# times its diagonal are shifted: a georeferenced folder (UTM, ~1e6 m) is 1e3 to 1e6
# times as far as it is large, scans in their scanner frames rarely more than once.
LOCAL_FRAME_RATIO = 10.0


def local_frame_offset(scans: list[Scan]) -> np.ndarray | None:
    """The offset ((3,) float64) to subtract from every scan, or None when the scans'
    common box lies within ``LOCAL_FRAME_RATIO`` diagonals of the origin.

    It is the centre of that box rounded to the power of ten at or above its diagonal
    (at least 1): a round number, the same for a folder and that folder moved by any
    multiple of it (a georeferenced set and its local twin see the same coordinates).
    """
    lo = np.min([s.points.min(axis=0) for s in scans], axis=0)
    hi = np.max([s.points.max(axis=0) for s in scans], axis=0)
    centre = (lo + hi) / 2.0
    size = max(float(np.linalg.norm(hi - lo)), np.finfo(float).tiny)
    if np.max(np.abs(centre)) <= LOCAL_FRAME_RATIO * size:
        return None
    step = max(1.0, 10.0 ** np.ceil(np.log10(size)))
    return np.round(centre / step) * step


def to_local_frame(loaded: Loaded) -> Loaded:
    """``loaded`` with its scans (points, sensor origins, stored poses) and its truth
    shifted by :func:`local_frame_offset` (in float64), the offset recorded in
    ``Loaded.local_frame_offset`` and on every scan; unchanged when there is none.

    The poses found for the shifted scans are put back into the files' frame by
    :func:`mvreg.io.poses.pose_with_offset` (``Registration.T_world_scan_in_file_frame``).
    """
    offset = local_frame_offset(loaded.scans)
    if offset is None:
        return loaded
    loaded.scans = [_shift_scan(s, offset) for s in loaded.scans]
    if loaded.truth:
        loaded.truth = {n: pose_with_offset(T, -offset) for n, T in loaded.truth.items()}
    loaded.local_frame_offset = offset
    return loaded


def _shift_scan(scan: Scan, offset: np.ndarray) -> Scan:
    origin, hint = scan.sensor_origin, scan.T_world_scan_hint
    return replace(
        scan,
        points=scan.points - offset,
        sensor_origin=None if origin is None else origin - offset,
        T_world_scan_hint=None if hint is None else pose_with_offset(hint, -offset),
        local_frame_offset=offset.copy(),
    )


# A point this many times further from its scan's median point than the scan's median
# distance from it is a stray (a glitch at 1e9): no scan spans four orders of magnitude.
FAR_STRAY_FACTOR = 1e4


def drop_far_strays(scan: Scan, min_points: int) -> Scan:
    """``scan`` without points further than ``FAR_STRAY_FACTOR`` times its median radius
    from its median point (counted in ``num_dropped_far``); the same object when none is.
    One such point otherwise makes the voxel grids of every later stage impossibly large."""
    centre = np.median(scan.points, axis=0)
    with np.errstate(over="ignore", invalid="ignore"):  # garbage bodies: checked below
        r = np.linalg.norm(scan.points - centre, axis=1)
    radius = float(np.median(r))
    far = ~(r <= FAR_STRAY_FACTOR * max(radius, np.finfo(float).tiny))
    if not np.any(far):
        return check_spacing(scan)
    keep = ~far
    if keep.sum() < min_points:
        raise TooFewPointsError(
            scan.path,
            f"only {int(keep.sum())} points away from far strays, fewer than the minimum "
            f"of {min_points} (min_points)",
            scan=scan.name,
        )
    return check_spacing(
        replace(
            scan,
            points=scan.points[keep],
            normals=None if scan.normals is None else scan.normals[keep],
            colors=None if scan.colors is None else scan.colors[keep],
            num_dropped_far=int(far.sum()),
        )
    )


# A scan whose extent is more than this many times its point spacing is not a sampled
# surface but a misread body (random bytes, the wrong byte order): their values spread
# over hundreds of orders of magnitude. Real scans stay below ~1e6 (a 1 km TLS scan at
# 1 mm spacing); float64 keeps ~16 digits.
SPACING_RATIO_MAX = 1e10
_SPACING_SAMPLE = 4096


def check_spacing(scan: Scan) -> Scan:
    """``scan`` unchanged, or ScanFileError naming its file when its extent about its
    median point exceeds ``SPACING_RATIO_MAX`` times its median nearest-neighbour spacing
    (measured on an evenly strided sample of distinct points: sparser, so never stricter)."""
    from scipy.spatial import cKDTree

    pts = scan.points[:: max(1, len(scan.points) // _SPACING_SAMPLE)]
    pts = np.unique(pts, axis=0)
    if len(pts) < 2:
        return scan
    with np.errstate(over="ignore", invalid="ignore"):
        local = pts - np.median(pts, axis=0)
        extent = float(np.max(np.linalg.norm(local, axis=1)))
        spacing = float(np.median(cKDTree(local).query(local, k=2)[0][:, 1]))
    if np.isfinite(extent) and extent <= SPACING_RATIO_MAX * spacing:
        return scan
    spread = f"{extent:.3g}" if np.isfinite(extent) else "more than float64 can square"
    raise ScanFileError(
        scan.path,
        f"not a sampled surface: the points spread over {spread} with a median "
        f"spacing of {spacing:.3g} (more than {SPACING_RATIO_MAX:.0e} times it); "
        "a corrupt body or the wrong byte order?",
    )


def _load_folder(folder: Path, min_points, max_points, truth, prog) -> Loaded:
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder of scans")
    listing = scan_folder(folder)
    if not listing.files:
        raise InputError(f"{folder}: no scan files found")
    prog.stage("load", len(listing.files))

    def load(f):  # (scans, rejected) of one file
        out, left = [], []
        for scan in load_scan_file(f, min_points, max_points, rejected=left):
            try:
                out.append(drop_far_strays(scan, min_points))
            except TooFewPointsError as e:
                left.append(e)
        return out, left

    scans, rejected = [], []
    # Two files at a time (parsing and checking release the GIL for much of their time);
    # results taken in file order, so the scans' order and the first error are as read in
    # turn.
    with ThreadPoolExecutor(LOAD_THREADS) as pool:
        for out, left in pool.map(load, listing.files):
            scans += out
            rejected += left
            prog.advance()
    gt = folder / "ground_truth.json"
    if truth is None and (gt.exists() or gt.is_symlink()):  # a dangling link is an error
        truth = read_poses_json(gt)
    left_out = [
        {"file": display_path(Path(e.path).name), "reason": e.reason, "scan": e.scan}
        for e in rejected
    ]
    return Loaded(scans, str(folder), truth, listing.skipped_report() + left_out)


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
