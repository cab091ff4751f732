"""Timestamps of a sequence and the gaps in it.

``timestamps.txt`` in the folder (one number per line, one per scan in scan order; or
``name number`` lines), else the last number in each file name, else the scan index.
Only ratios of time steps are used, so the unit does not matter. A time step above
``gap_factor`` times the median step is a gap (a missing scan, a pause).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mvreg.errors import InputError

TIMESTAMPS_FILE = "timestamps.txt"


_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def timestamps_from_names(names: Sequence[str]) -> np.ndarray | None:
    """(M,) the last number in each file name (without its suffix), or None when a name
    has none or the numbers do not increase strictly in the given order."""
    out = []
    for n in names:
        found = _NUMBER.findall(Path(n).stem)
        if not found:
            return None
        out.append(float(found[-1]))
    t = np.array(out)
    return t if len(t) < 2 or np.all(np.diff(t) > 0) else None


def read_timestamps_file(path: str | Path, names: Sequence[str]) -> np.ndarray | None:
    """Times of ``names`` from a timestamps file (see the module docstring).

    Returns (M,) float64, or None when the file has one number per line but not one per
    scan (a scan file was removed or added: which line is whose is unknown).
    Raises:
        InputError: unreadable or unparsable, a scan missing from a ``name time`` file,
            or times that do not increase strictly in scan order.
    """
    path = Path(path)
    try:
        lines = [ln.split() for ln in path.read_text().splitlines()]
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read timestamps ({e})") from None
    lines = [ln for ln in lines if ln and not ln[0].startswith("#")]
    try:
        if all(len(ln) == 1 for ln in lines):
            values = [float(ln[0]) for ln in lines]
            if len(values) != len(names):
                return None
            t = np.array(values)
        elif all(len(ln) == 2 for ln in lines):
            by_name = {ln[0]: float(ln[1]) for ln in lines}
            missing = [n for n in names if n not in by_name]
            if missing:
                raise InputError(
                    f"{path}: no time for {len(missing)} scan(s): {', '.join(missing[:5])}"
                )
            t = np.array([by_name[n] for n in names])
        else:
            raise InputError(f"{path}: expected one 'time' or one 'name time' per line")
    except ValueError as e:
        raise InputError(f"{path}: not a number ({e})") from None
    if not np.all(np.isfinite(t)):
        raise InputError(f"{path}: NaN or inf time")
    if np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise InputError(
            f"{path}: times must increase in scan order ({names[k]}: {t[k]!r}, "
            f"{names[k + 1]}: {t[k + 1]!r})"
        )
    return t


def sequence_timestamps(scans, folder, given, warnings: list[str]) -> tuple[np.ndarray, str]:
    names = [s.name for s in scans]
    if given is not None:
        t = np.asarray(given, dtype=np.float64).reshape(-1)
        if len(t) != len(scans) or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise InputError(
                f"timestamps: need {len(scans)} finite, strictly increasing times, got {len(t)}"
            )
        return t, "given"
    if folder is not None and (folder / TIMESTAMPS_FILE).is_file():
        t = read_timestamps_file(folder / TIMESTAMPS_FILE, names)
        if t is not None:
            return t, TIMESTAMPS_FILE
        warnings.append(
            f"{TIMESTAMPS_FILE} has one time per line but not one per scan ({len(scans)} "
            "scans): ignored"
        )
    t = timestamps_from_names(names)
    if t is not None:
        return t, "file names"
    warnings.append("no timestamps (file names carry no increasing numbers): scan index used")
    return np.arange(len(scans), dtype=np.float64), "index"


def find_gaps(times: np.ndarray, gap_factor: float) -> list[dict]:
    """Time steps above ``gap_factor`` times the median step.

    Args:
        times: (M,) strictly increasing.
    Returns:
        one dict per gap: ``after`` (index k of the scan before it), ``time_step``,
        ``median_time_step``, ``missing_scans`` (estimated: step / median - 1, rounded).
    """
    dt = np.diff(np.asarray(times, dtype=np.float64))
    if len(dt) == 0:
        return []
    med = float(np.median(dt))
    return [
        {
            "after": int(k),
            "time_step": float(dt[k]),
            "median_time_step": med,
            "missing_scans": max(0, int(round(dt[k] / med)) - 1),
        }
        for k in np.flatnonzero(dt > gap_factor * med)
    ]
