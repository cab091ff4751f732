"""Virtual range scanners by ray casting (open3d ``RaycastingScene``, first hit only).

Two sensor models, both with the sensor at the origin of its own frame:

- :class:`PinholeScanner`: a range camera. OpenCV camera frame: +z forward (optical
  axis), +x right, +y down. ``width`` x ``height`` pixels, horizontal field of view
  ``fov_x_deg``, square pixels.
- :class:`LidarScanner`: a spinning LiDAR. Usual LiDAR frame: +z is the spin axis (up),
  +x forward (azimuth 0), +y left. ``beams`` rows spread evenly over
  ``vertical_fov_deg``, ``horizontal_steps`` columns over 360 degrees.

Noise model, applied in this order to the rays that hit:
  1. grazing returns are lost: hits whose incidence angle exceeds ``max_incidence_deg``;
  2. dropout: each remaining point is removed with probability ``dropout``;
  3. range noise: the range along the ray gets N(0, sigma^2), sigma = ``range_sigma``
     (callers set it to ``noise * object diagonal``); the point moves along its ray;
  4. outliers: a fraction ``outliers`` of the points gets a range drawn uniformly between
     the scan's nearest and farthest hit (points floating along their rays, as
     mixed pixels and multipath returns do).

The ray caster works in float32. Hit points are refined in float64 by intersecting each
ray with the plane of the triangle it hit, so noise-free points lie on the float64 mesh.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
import trimesh

from mvreg.errors import ConfigError


@dataclass(frozen=True)
class PinholeScanner:
    """Pinhole range camera (OpenCV frame: +z forward, +x right, +y down).

    Attributes:
        width, height: image size in pixels.
        fov_x_deg: horizontal field of view, degrees.
        max_range: rays longer than this return nothing (mesh units; inf = unlimited).
    """

    width: int
    height: int
    fov_x_deg: float
    max_range: float = float("inf")

    kind = "pinhole"

    def __post_init__(self):
        if self.width < 1 or self.height < 1:
            raise ConfigError(f"pinhole resolution must be >= 1x1, not {self.width}x{self.height}")
        if not 0.0 < self.fov_x_deg < 180.0:
            raise ConfigError(
                f"pinhole field of view must be in (0, 180) deg, not {self.fov_x_deg}"
            )
        if not self.max_range > 0.0:
            raise ConfigError(f"max_range must be > 0, not {self.max_range}")

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (fx = fy)."""
        return 0.5 * self.width / np.tan(0.5 * np.radians(self.fov_x_deg))

    def ray_directions(self) -> np.ndarray:
        """Unit ray directions in the sensor frame, (height * width, 3) float64, row-major."""
        return _pinhole_directions(self.width, self.height, float(self.focal_px))

    def describe(self) -> dict:
        """Parameters for ``synth.json``."""
        return {
            "kind": self.kind,
            "width_px": self.width,
            "height_px": self.height,
            "fov_x_deg": self.fov_x_deg,
            "focal_px": float(self.focal_px),
            "max_range": _finite_or_none(self.max_range),
            "frame": "OpenCV camera: +z forward, +x right, +y down",
        }


@dataclass(frozen=True)
class LidarScanner:
    """Spinning LiDAR (frame: +z spin axis / up, +x azimuth 0 / forward, +y left).

    Attributes:
        beams: number of laser rows.
        horizontal_steps: columns per full 360-degree turn.
        vertical_fov_deg: (lowest, highest) beam elevation, degrees.
        max_range: rays longer than this return nothing (scene units).
        min_range: returns closer than this are discarded (scene units).
    """

    beams: int
    horizontal_steps: int
    vertical_fov_deg: tuple[float, float] = (-25.0, 15.0)
    max_range: float = float("inf")
    min_range: float = 0.0

    kind = "lidar"

    def __post_init__(self):
        if self.beams < 1 or self.horizontal_steps < 1:
            raise ConfigError(
                f"lidar needs >= 1 beam and >= 1 step, not {self.beams} x {self.horizontal_steps}"
            )
        lo, hi = self.vertical_fov_deg
        if not -90.0 <= lo <= hi <= 90.0:
            raise ConfigError(f"lidar vertical field of view must lie in [-90, 90], not {lo, hi}")
        if not self.max_range > self.min_range >= 0.0:
            raise ConfigError(
                f"lidar needs 0 <= min_range < max_range, not {self.min_range}, {self.max_range}"
            )

    def ray_directions(self) -> np.ndarray:
        """Unit ray directions in the sensor frame, (beams * horizontal_steps, 3) float64.

        Ordered beam by beam (lowest first), azimuth 0..360 degrees counter-clockwise.
        """
        lo, hi = self.vertical_fov_deg
        return _lidar_directions(self.beams, self.horizontal_steps, float(lo), float(hi))

    def describe(self) -> dict:
        """Parameters for ``synth.json``."""
        return {
            "kind": self.kind,
            "beams": self.beams,
            "horizontal_steps": self.horizontal_steps,
            "vertical_fov_deg": list(self.vertical_fov_deg),
            "max_range": _finite_or_none(self.max_range),
            "min_range": self.min_range,
            "frame": "LiDAR: +z spin axis (up), +x forward, +y left",
        }


Scanner = PinholeScanner | LidarScanner


@dataclass(frozen=True)
class NoiseModel:
    """Scanner imperfections (see the module docstring for the order they apply in).

    Attributes:
        range_sigma: standard deviation of the range noise along the ray (mesh units).
        outliers: fraction of the kept points turned into outliers, in [0, 1).
        dropout: probability that a point is lost, in [0, 1).
        max_incidence_deg: hits seen at a larger angle from the surface normal are lost.
    """

    range_sigma: float = 0.0
    outliers: float = 0.0
    dropout: float = 0.0
    max_incidence_deg: float = 85.0

    def __post_init__(self):
        if not (np.isfinite(self.range_sigma) and self.range_sigma >= 0.0):
            raise ConfigError(f"range noise must be >= 0, not {self.range_sigma}")
        if not 0.0 <= self.outliers < 1.0:
            raise ConfigError(f"outliers fraction must be in [0, 1), not {self.outliers}")
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"dropout must be in [0, 1), not {self.dropout}")
        if not 0.0 < self.max_incidence_deg <= 90.0:
            raise ConfigError(f"max_incidence_deg must be in (0, 90], not {self.max_incidence_deg}")


@dataclass
class RawScan:
    """One simulated scan in its sensor frame.

    Attributes:
        points: (N, 3) float64, sensor frame.
        normals: (N, 3) float64 unit surface normals (sensor frame, facing the sensor).
        is_outlier: (N,) bool, True for the points replaced by outliers.
        n_rays: number of rays cast.
    """

    points: np.ndarray
    normals: np.ndarray
    is_outlier: np.ndarray
    n_rays: int = 0
    extra: dict = field(default_factory=dict)


class MeshRaycaster:
    """A ray-casting scene over one float64 mesh, with float64 hit refinement.

    Internally the scene is built around the mesh's bounding-box centre so float32 loses
    as little as possible; callers use mesh coordinates throughout.
    """

    def __init__(self, mesh: trimesh.Trimesh):
        import open3d as o3d

        self._o3d = o3d
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.faces = np.asarray(mesh.faces, dtype=np.int64)
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        self.centre = 0.5 * (lo + hi)
        # Bounding sphere (slightly padded against rounding) for ray culling.
        self.radius = 0.5 * float(np.linalg.norm(hi - lo)) * (1.0 + 1e-6) + 1e-12
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor((self.vertices - self.centre).astype(np.float32)),
            o3d.core.Tensor(self.faces.astype(np.uint32)),
        )
        a, b, c = (self.vertices[self.faces[:, k]] for k in range(3))
        n = np.cross(b - a, c - a)
        self.face_normals = n / np.linalg.norm(n, axis=1, keepdims=True)

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit of each ray.

        Args:
            origin: (3,) float64 ray origin (mesh coordinates).
            directions: (M, 3) float64 unit directions (mesh coordinates).
        Returns:
            ranges (M,) float64 (inf where nothing is hit) and triangle ids (M,) int64
            (-1 where nothing is hit).
        """
        o3d = self._o3d
        ranges = np.full(len(directions), np.inf)
        ids = np.full(len(directions), -1, dtype=np.int64)
        # Only rays inside the cone around the bounding sphere can hit: skip the others
        # (a LiDAR sees a small object in a few degrees of its 360-degree sweep).
        to_centre = self.centre - origin
        dist = float(np.linalg.norm(to_centre))
        if dist > self.radius:
            cos_cone = np.sqrt(1.0 - (self.radius / dist) ** 2)
            cos_angle = np.einsum("ij,j->i", directions, to_centre / dist)
            cast = np.flatnonzero(cos_angle >= cos_cone - 1e-9)
        else:
            cast = np.arange(len(directions))
        if len(cast) == 0:
            return ranges, ids
        directions = directions[cast]
        rays = np.empty((len(cast), 6), dtype=np.float32)
        rays[:, :3] = (origin - self.centre).astype(np.float32)
        rays[:, 3:] = directions.astype(np.float32)
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))
        t32 = hit["t_hit"].numpy().astype(np.float64)
        sub_ids = hit["primitive_ids"].numpy().astype(np.int64)
        ok = np.isfinite(t32)
        ids[cast[ok]] = sub_ids[ok]
        # Refine in float64: intersect the ray with the plane of the triangle it hit.
        face = sub_ids[ok]
        n = self.face_normals[face]
        a = self.vertices[self.faces[face, 0]]
        denom = np.einsum("ij,ij->i", n, directions[ok])
        with np.errstate(divide="ignore", invalid="ignore"):
            t64 = np.einsum("ij,ij->i", n, a - origin) / denom
        # Keep float32's answer where the plane intersection is ill-conditioned (grazing).
        tol = 1e-4 * (np.abs(t32[ok]) + 1e-12)
        good = np.isfinite(t64) & (np.abs(t64 - t32[ok]) <= tol)
        ranges[cast[ok]] = np.where(good, t64, t32[ok])
        return ranges, ids


def simulate_scan(
    raycaster: MeshRaycaster,
    scanner: Scanner,
    T_world_sensor: np.ndarray,
    noise: NoiseModel,
    rng: np.random.Generator,
) -> RawScan:
    """Cast one scan and apply the noise model.

    Args:
        raycaster: the scene (mesh coordinates = world).
        scanner: sensor model.
        T_world_sensor: (4, 4) float64 pose of the sensor (world from sensor).
        noise: imperfections to apply.
        rng: random generator for dropout, range noise and outliers.
    Returns:
        :class:`RawScan` with points and normals in the sensor frame.
    """
    d_sensor = scanner.ray_directions()
    R = T_world_sensor[:3, :3]
    origin = T_world_sensor[:3, 3]
    d_world = rotate_rows(R, d_sensor)
    ranges, ids = raycaster.cast(origin, d_world)
    min_range = getattr(scanner, "min_range", 0.0)
    keep = np.isfinite(ranges) & (ranges <= scanner.max_range) & (ranges > min_range)
    n_world = raycaster.face_normals[np.where(keep, ids, 0)]
    cos_incidence = -np.einsum("ij,ij->i", n_world, d_world)
    # Back faces (cos < 0) count too: open meshes are seen from both sides.
    keep &= np.abs(cos_incidence) >= np.cos(np.radians(noise.max_incidence_deg))

    idx = np.flatnonzero(keep)
    if noise.dropout > 0.0:
        idx = idx[rng.random(len(idx)) >= noise.dropout]
    r = ranges[idx]
    if noise.range_sigma > 0.0:
        r = r + rng.normal(0.0, noise.range_sigma, len(idx))
    is_outlier = np.zeros(len(idx), dtype=bool)
    if noise.outliers > 0.0 and len(idx) > 0:
        n_out = int(round(noise.outliers * len(idx)))
        which = rng.choice(len(idx), size=n_out, replace=False)
        r_lo, r_hi = float(ranges[idx].min()), float(ranges[idx].max())
        r[which] = rng.uniform(r_lo, r_hi, n_out)
        is_outlier[which] = True
    points = d_sensor[idx] * r[:, None]
    normals = rotate_rows(R.T, n_world[idx])  # world -> sensor
    normals *= np.where(np.einsum("ij,ij->i", normals, d_sensor[idx]) > 0.0, -1.0, 1.0)[:, None]
    return RawScan(points, normals, is_outlier, n_rays=len(d_sensor))


def hit_fraction(raycaster: MeshRaycaster, scanner: Scanner, T_world_sensor: np.ndarray) -> float:
    """Fraction of the scanner's rays that hit the mesh (no noise), for resolution calibration."""
    d_world = rotate_rows(T_world_sensor[:3, :3], scanner.ray_directions())
    ranges, _ = raycaster.cast(T_world_sensor[:3, 3], d_world)
    return float(np.mean(np.isfinite(ranges) & (ranges <= scanner.max_range)))


def fit_pinhole(
    raycaster: MeshRaycaster,
    T_world_sensors: list[np.ndarray],
    target_centre: np.ndarray,
    bounding_radius: float,
    points_per_scan: int,
    keep_fraction: float = 1.0,
    aspect: float = 4.0 / 3.0,
) -> PinholeScanner:
    """A range camera that frames the object from every view and gives ~``points_per_scan``.

    The vertical field of view covers the object's bounding sphere from the nearest view
    (plus 10%); the resolution is set from the mean hit fraction of a coarse probe image
    over all views, divided by ``keep_fraction`` (the expected share surviving dropout).

    Args:
        T_world_sensors: poses of all views, each (4, 4).
        target_centre: (3,) centre of the object's bounding sphere.
        bounding_radius: its radius (mesh units).
        points_per_scan: wanted mean number of points per scan.
    """
    nearest = min(float(np.linalg.norm(T[:3, 3] - target_centre)) for T in T_world_sensors)
    if nearest <= bounding_radius:
        raise ConfigError(
            f"a viewpoint is inside the object's bounding sphere (distance {nearest:.4g} <= "
            f"radius {bounding_radius:.4g}); increase the distance"
        )
    half_fov_y = 1.1 * np.arcsin(bounding_radius / nearest)
    fov_x = 2.0 * np.degrees(np.arctan(aspect * np.tan(half_fov_y)))
    fov_x = float(min(fov_x, 170.0))
    probe = PinholeScanner(width=int(round(64 * aspect)), height=64, fov_x_deg=fov_x)
    fraction = float(np.mean([hit_fraction(raycaster, probe, T) for T in T_world_sensors]))
    fraction = max(fraction, 1e-3)
    n_rays = points_per_scan / (fraction * keep_fraction)
    height = max(1, int(round(np.sqrt(n_rays / aspect))))
    width = max(1, int(round(height * aspect)))
    return PinholeScanner(width=width, height=height, fov_x_deg=fov_x)


def fit_lidar(
    raycaster: MeshRaycaster,
    T_world_sensors: list[np.ndarray],
    target_centre: np.ndarray,
    bounding_radius: float,
    points_per_scan: int,
    keep_fraction: float = 1.0,
) -> LidarScanner:
    """A LiDAR whose beams cover the object from every view, giving ~``points_per_scan``.

    The views must look at the object along +x (see ``placement``). The vertical field of
    view spans the bounding sphere from the nearest view; beams and horizontal steps are
    scaled together (same angular spacing in both directions) from a coarse probe.
    """
    nearest = min(float(np.linalg.norm(T[:3, 3] - target_centre)) for T in T_world_sensors)
    if nearest <= bounding_radius:
        raise ConfigError(
            f"a viewpoint is inside the object's bounding sphere (distance {nearest:.4g} <= "
            f"radius {bounding_radius:.4g}); increase the distance"
        )
    half_deg = float(np.degrees(1.1 * np.arcsin(bounding_radius / nearest)))
    vfov = (-half_deg, half_deg)
    probe_beams = 32
    probe_steps = int(round(probe_beams * 360.0 / (2.0 * half_deg)))
    probe = LidarScanner(probe_beams, probe_steps, vfov)
    fraction = float(np.mean([hit_fraction(raycaster, probe, T) for T in T_world_sensors]))
    hits = max(fraction * probe_beams * probe_steps, 1.0)
    scale = np.sqrt(points_per_scan / (hits * keep_fraction))
    return LidarScanner(
        beams=max(1, int(round(probe_beams * scale))),
        horizontal_steps=max(8, int(round(probe_steps * scale))),
        vertical_fov_deg=vfov,
    )


@functools.lru_cache(maxsize=4)
def _pinhole_directions(width: int, height: int, focal_px: float) -> np.ndarray:
    u = (np.arange(width) + 0.5 - 0.5 * width) / focal_px
    v = (np.arange(height) + 0.5 - 0.5 * height) / focal_px
    uu, vv = np.meshgrid(u, v)
    d = np.column_stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d.flags.writeable = False  # cached and shared between scans
    return d


@functools.lru_cache(maxsize=4)
def _lidar_directions(beams: int, steps: int, lo_deg: float, hi_deg: float) -> np.ndarray:
    lo, hi = np.radians(lo_deg), np.radians(hi_deg)
    elevation = np.array([0.5 * (lo + hi)]) if beams == 1 else np.linspace(lo, hi, beams)
    azimuth = 2.0 * np.pi * np.arange(steps) / steps
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    el, az = el.ravel(), az.ravel()
    d = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    d.flags.writeable = False  # cached and shared between scans
    return d


def rotate_rows(R: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """``vectors @ R.T`` for (N, 3) rows and a (3, 3) matrix, without BLAS.

    einsum's own loop is deterministic and avoids BLAS thread start-up, which dominates
    for (N, 3) x (3, 3) products on a busy machine.
    """
    return np.einsum("ij,kj->ik", vectors, R)


def _finite_or_none(x: float):
    return float(x) if np.isfinite(x) else None
