"""Where the virtual scanner stands: sphere, turntable, random or explicit viewpoints.

Distances are multiples of the object's bounding-box diagonal, measured from the
bounding-box centre, so placements work whatever the mesh units. Each viewpoint becomes
a sensor pose ``T_world_sensor`` (world from sensor, 4x4) looking at the target:

- pinhole: +z (optical axis) towards the target, +y (image down) against ``up``;
- lidar: +x towards the target, +z (spin axis) along ``up``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mvreg.errors import ConfigError

PLACEMENTS = ("sphere", "turntable", "random", "explicit")
MAX_DISTANCE = 1000.0
"""Largest sensor distance, in object diagonals (beyond it the object is a few pixels)."""


@dataclass
class Viewpoints:
    """Sensor positions and poses.

    Attributes:
        positions: (N, 3) float64 sensor positions (mesh units).
        T_world_sensor: (N, 4, 4) float64 sensor poses (world from sensor).
        placement: how they were chosen (one of ``PLACEMENTS``).
    """

    positions: np.ndarray
    T_world_sensor: np.ndarray
    placement: str

    def __len__(self) -> int:
        return len(self.positions)


def make_viewpoints(
    placement: str,
    views: int,
    centre: np.ndarray,
    diagonal: float,
    *,
    distance: float = 1.5,
    scanner: str = "pinhole",
    rng: np.random.Generator | None = None,
    elevation_deg: float = 20.0,
    axis=(0.0, 0.0, 1.0),
    positions: np.ndarray | None = None,
) -> Viewpoints:
    """Sensor poses looking at ``centre``.

    Args:
        placement: ``"sphere"`` (a spiral over the whole sphere, consecutive views
            neighbours, like a hand-held session), ``"turntable"`` (a ring around ``axis``
            at ``elevation_deg``), ``"random"`` (uniform directions, distance jittered by
            +-20%, random roll; needs ``rng``) or ``"explicit"`` (``positions`` given).
        views: number of views (ignored for ``"explicit"``).
        centre: (3,) point looked at (mesh units).
        diagonal: object bounding-box diagonal (mesh units).
        distance: sensor distance from ``centre`` in diagonals.
        scanner: ``"pinhole"`` or ``"lidar"`` (decides which sensor axis looks at the target).
        axis: (3,) up direction of the turntable and the "up" hint of every view.
        positions: (N, 3) absolute sensor positions (mesh units) for ``"explicit"``.
    Returns:
        :class:`Viewpoints`.
    Raises:
        ConfigError: unknown placement, views < 1, distance <= 0.5 (inside the object) or
            > MAX_DISTANCE, elevation outside [-90, 90] degrees,
            bad explicit positions.
    """
    centre = np.asarray(centre, dtype=np.float64)
    up = _unit(np.asarray(axis, dtype=np.float64), "axis")
    if placement not in PLACEMENTS:
        raise ConfigError(f"unknown placement {placement!r}; choose one of {', '.join(PLACEMENTS)}")
    if scanner not in ("pinhole", "lidar"):
        raise ConfigError(f"unknown scanner {scanner!r}; choose pinhole or lidar")
    if placement != "explicit":
        if views < 1:
            raise ConfigError(f"views must be >= 1, not {views}")
        if not (np.isfinite(distance) and 0.5 < distance <= MAX_DISTANCE):
            raise ConfigError(
                f"distance must be in (0.5, {MAX_DISTANCE:g}] object diagonals (the sensor "
                f"outside the object, not absurdly far), not {distance}"
            )
        if not (np.isfinite(elevation_deg) and -90.0 <= elevation_deg <= 90.0):
            raise ConfigError(f"elevation must be in [-90, 90] degrees, not {elevation_deg}")
    radius = distance * diagonal
    rolls = np.zeros(max(views, 0))
    if placement == "sphere":
        pos = centre + radius * _spiral_directions(views, up)
    elif placement == "turntable":
        pos = centre + radius * _ring_directions(views, up, elevation_deg)
    elif placement == "random":
        if rng is None:
            raise ConfigError("random placement needs a random generator")
        d = rng.standard_normal((views, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pos = centre + radius * d * rng.uniform(0.8, 1.2, (views, 1))
        rolls = rng.uniform(-np.pi, np.pi, views)
    else:
        if positions is None:
            raise ConfigError("explicit placement needs viewpoint positions")
        pos = np.asarray(positions, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3 or len(pos) < 1:
            raise ConfigError(f"explicit viewpoints must be an (N, 3) array, not {pos.shape}")
        if not np.all(np.isfinite(pos)):
            raise ConfigError("explicit viewpoints contain NaN or inf")
        too_close = np.linalg.norm(pos - centre, axis=1) <= 0.5 * diagonal
        if np.any(too_close):
            raise ConfigError(
                f"explicit viewpoint {int(np.argmax(too_close))} is within half a diagonal "
                "of the object centre (inside the object)"
            )
        rolls = np.zeros(len(pos))
    poses = np.stack(
        [
            look_at(p, centre, up, scanner=scanner, roll=roll)
            for p, roll in zip(pos, rolls, strict=True)
        ]
    )
    return Viewpoints(positions=pos, T_world_sensor=poses, placement=placement)


def look_at(
    eye: np.ndarray,
    target: np.ndarray,
    up: np.ndarray,
    *,
    scanner: str = "pinhole",
    roll: float = 0.0,
) -> np.ndarray:
    """(4, 4) world-from-sensor pose at ``eye`` looking at ``target``.

    Pinhole: +z towards the target, +y against ``up``. LiDAR: +x towards the target, +z
    along ``up``. ``roll`` (radians) turns the sensor about its viewing axis.
    """
    forward = _unit(np.asarray(target, dtype=np.float64) - eye, "view direction")
    up = np.asarray(up, dtype=np.float64)
    if abs(float(forward @ up)) > 0.999:  # looking straight along up: any perpendicular will do
        up = np.eye(3)[int(np.argmin(np.abs(forward)))]
    up_perp = _unit(up - (up @ forward) * forward, "up")
    side = np.cross(forward, up_perp)  # right-handed: forward x up = right
    c, s = np.cos(roll), np.sin(roll)
    up_perp, side = c * up_perp + s * side, c * side - s * up_perp
    T = np.eye(4)
    T[:3, 3] = eye
    if scanner == "pinhole":
        # OpenCV: x right, y down, z forward; x = y x z.
        T[:3, 0], T[:3, 1], T[:3, 2] = side, -up_perp, forward
    else:
        # LiDAR: x forward, z up, y = z x x (left).
        T[:3, 0], T[:3, 1], T[:3, 2] = forward, np.cross(up_perp, forward), up_perp
    return T


def _spiral_directions(n: int, up: np.ndarray) -> np.ndarray:
    """(n, 3) unit vectors on a generalized spiral (Saff & Kuijlaars) from top to bottom.

    Evenly spread, and consecutive points are neighbours (as in a hand-held sweep). The
    poles themselves are avoided (half a step in from each end).
    """
    h = 1.0 - (2.0 * np.arange(n) + 1.0) / n  # cos(polar angle), in (-1, 1)
    polar = np.arccos(h)
    azimuth = np.zeros(n)
    for k in range(1, n):
        azimuth[k] = azimuth[k - 1] + 3.6 / np.sqrt(n) / np.sqrt(max(1.0 - h[k] ** 2, 1e-12))
    if n == 1:
        polar[:] = 0.5 * np.pi
    local = np.column_stack(
        [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)]
    )
    return local @ _frame_with_z(up).T


def _ring_directions(n: int, up: np.ndarray, elevation_deg: float) -> np.ndarray:
    if not -90.0 < elevation_deg < 90.0:
        raise ConfigError(f"turntable elevation must be in (-90, 90) deg, not {elevation_deg}")
    el = np.radians(elevation_deg)
    az = 2.0 * np.pi * np.arange(n) / n
    local = np.column_stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(n, np.sin(el))]
    )
    return local @ _frame_with_z(up).T


def _frame_with_z(z: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose third column is ``z`` (columns: x, y, z)."""
    helper = np.eye(3)[int(np.argmin(np.abs(z)))]
    x = _unit(np.cross(helper, z), "axis")
    return np.column_stack([x, np.cross(z, x), z])


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if not (np.isfinite(n) and n > 0.0):
        raise ConfigError(f"{what} must be a non-zero finite vector, not {v.tolist()}")
    return v / n
