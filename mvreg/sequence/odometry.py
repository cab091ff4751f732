"""KISS-ICP odometry over the scans in order, its settings derived from the data.

``max_range`` = the largest point range of the sequence, voxel = ``odometry_voxel_ranges``
times it (KISS-ICP's own default ratio 1/100), initial threshold 2 voxels and minimum
motion 0.1 voxel; deskewing off (scans carry no per-point times); the constant-velocity
prediction rescaled by the ratio of time steps.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from mvreg.config.sequence import SequenceConfig
from mvreg.errors import InputError


@dataclass
class Odometry:
    """KISS-ICP poses of a sequence.

    T_odom_scan: (M, 4, 4) float64, scan k's pose in the odometry frame (scan 0 = identity).
    max_range, voxel_size: the KISS-ICP settings derived from the data (data units).
    seconds: wall time of the odometry. config: KISS-ICP's resolved configuration.
    """

    T_odom_scan: np.ndarray
    max_range: float
    voxel_size: float
    seconds: float
    config: dict


def scale_motion(T: np.ndarray, s: float) -> np.ndarray:
    """The rigid motion ``T`` (4, 4) scaled by ``s`` (rotation angle and translation)."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(s * Rotation.from_matrix(T[:3, :3]).as_rotvec()).as_matrix()
    out[:3, 3] = s * T[:3, 3]
    return out


def kiss_icp_odometry(
    points: Sequence[np.ndarray],
    times: np.ndarray,
    cfg: SequenceConfig | None = None,
    advance: Callable[[], None] | None = None,
) -> Odometry:
    """KISS-ICP over the scans in order (settings from the data, see the module docstring).

    Args:
        points: per scan, (N_k, 3) float64 in the sensor frame.
        times: (M,) strictly increasing; the constant-velocity prediction is scaled by
            the ratio of consecutive time steps.
    Returns:
        :class:`Odometry` with (M, 4, 4) poses, scan 0 at the identity.
    """
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    cfg = cfg or SequenceConfig()
    max_range = max(float(np.max(np.linalg.norm(p, axis=1))) for p in points)
    if not max_range > 0:
        raise InputError("all points are at the sensor origin: not range scans")
    voxel = cfg.odometry_voxel_ranges * max_range
    kiss_cfg = KISSConfig()
    kiss_cfg.data.max_range = 1.001 * max_range
    kiss_cfg.data.min_range = 0.0
    kiss_cfg.data.deskew = False
    kiss_cfg.mapping.voxel_size = voxel
    kiss_cfg.adaptive_threshold.initial_threshold = 2.0 * voxel
    kiss_cfg.adaptive_threshold.min_motion_th = 0.1 * voxel
    kiss_cfg.registration.max_num_threads = cfg.odometry_threads
    odometry = KissICP(kiss_cfg)
    start = time.perf_counter()
    poses = np.empty((len(points), 4, 4))
    dt = np.diff(np.asarray(times, dtype=np.float64))
    no_times = np.zeros(0)
    for k, p in enumerate(points):
        if k >= 2 and dt[k - 1] != dt[k - 2]:  # constant velocity in time, not per scan
            odometry.last_delta = scale_motion(odometry.last_delta, dt[k - 1] / dt[k - 2])
        odometry.register_frame(np.ascontiguousarray(p, dtype=np.float64), no_times)
        poses[k] = odometry.last_pose
        if advance is not None:
            advance()
    return Odometry(
        T_odom_scan=poses,
        max_range=max_range,
        voxel_size=voxel,
        seconds=time.perf_counter() - start,
        config=kiss_cfg.model_dump(mode="json"),
    )


def kiss_version() -> str | None:
    try:
        from importlib.metadata import version

        return version("kiss-icp")
    except Exception:  # metadata missing: report no version rather than fail
        return None
