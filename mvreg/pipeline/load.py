"""The load stage: scans from a folder (checked, natural order) or from point arrays.

Returns the scans, the source as text and the ground truth (``ground_truth.json`` in the
folder, used only to evaluate). Raises InputError / ScanFileError naming the culprit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvreg.errors import InputError
from mvreg.io.loaders import Scan, list_scan_files, load_scan


def load_source(source, names, min_points: int, truth, prog, what: str = "registration"):
    """Scans from a folder or from (N, 3) arrays, checked; the source as text; the truth
    (read from ``ground_truth.json`` in the folder when not given)."""
    if isinstance(source, (str, Path)):
        folder = Path(source)
        if not folder.is_dir():
            raise InputError(f"{folder}: not a folder of scans")
        files = list_scan_files(folder)
        if not files:
            raise InputError(f"{folder}: no scan files found")
        prog.stage("load", len(files))
        scans = []
        for f in files:
            scans.append(load_scan(f, min_points=min_points))
            prog.advance()
        if truth is None and (folder / "ground_truth.json").exists():
            from mvreg.io.poses import read_poses_json

            truth = read_poses_json(folder / "ground_truth.json")
        src = str(folder)
    else:
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
        src = None
    if len(scans) < 2:
        raise InputError(f"{source}: {what} needs at least 2 scans, found {len(scans)}")
    return scans, src, truth
