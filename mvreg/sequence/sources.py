"""Sequences from any source KISS-ICP's own dataloaders read (``sequence.dataloader``):
KITTI odometry folders, KITTI raw, nuScenes, MulRan, NCD, rosbag, MCAP, Ouster pcap, a
folder of ``.bin`` / ``.pcd`` / ``.ply`` files (``generic``), ...

Contract: :func:`read_dataloader` takes the dataloader's name, the path it reads and its
``sequence`` argument (KITTI's ``00`` ...), and returns the frames in time order as
(N_k, 3) float64 arrays in their sensor frames with a name per frame (the frame's file
stem where the dataloader has files, else ``frame_000000`` ...). A name KISS-ICP does not
know is a :class:`~mvreg.errors.ConfigError` listing the known ones; a source the
dataloader cannot read, or a frame without finite points, an
:class:`~mvreg.errors.InputError` naming the path (and the frame).
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np

from mvreg.errors import ConfigError, InputError


def dataloader_names() -> list[str]:
    from kiss_icp.datasets import available_dataloaders

    return sorted(available_dataloaders())


def read_dataloader(
    name: str,
    path: Path,
    sequence: str | None = None,
    max_frames: int | None = None,
    warnings: list[str] | None = None,
) -> tuple[list[np.ndarray], list[str]]:
    """(frames, names) of the source at ``path`` read by KISS-ICP's dataloader ``name``.
    With ``warnings`` (a list), rows with a NaN/inf coordinate are dropped and a warning
    naming the frame's file and the count is appended for each frame that had some."""
    known = dataloader_names()
    if name not in known:
        raise ConfigError(f"sequence.dataloader {name!r} is not one of {', '.join(known)}")
    from kiss_icp.datasets import dataset_factory

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder (for the {name} dataloader)")
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # the dataloaders print notices
            dataset = dataset_factory(dataloader=name, data_dir=path, sequence=sequence)
        count = len(dataset)
    except Exception as e:  # noqa: BLE001 - each dataloader raises its own errors
        raise InputError(f"{path}: the {name} dataloader cannot read it ({e})") from e
    count = count if max_frames is None else min(count, max_frames)
    files = getattr(dataset, "scan_files", None)
    frames, names = [], []
    for k in range(count):
        where = f"{files[k]}" if files is not None else f"{path}: frame {k}"
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                item = dataset[k]
        except Exception as e:  # noqa: BLE001
            raise InputError(f"{where}: not readable by the {name} dataloader ({e})") from e
        pts = np.asarray(item[0] if isinstance(item, tuple) else item, dtype=np.float64)
        pts = pts.reshape(-1, 3) if pts.size % 3 == 0 else pts
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"{where}: not a list of 3D points ({pts.shape})")
        finite = np.all(np.isfinite(pts), axis=1)
        if not np.any(finite):
            raise InputError(f"{where}: no point with finite coordinates")
        if warnings is not None and not finite.all():
            warnings.append(f"{where}: {int((~finite).sum())} points with a NaN or infinite "
                            "coordinate left out")  # fmt: skip
            pts = pts[finite]
        frames.append(pts)  # without ``warnings``: NaN/inf rows dropped by the load stage
        names.append(Path(str(files[k])).stem if files is not None else f"frame_{k:06d}")
    if len(frames) < 2:
        raise InputError(f"{path}: the {name} dataloader gives {len(frames)} frame(s); 2+ needed")
    return frames, names
