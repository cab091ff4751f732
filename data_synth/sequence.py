"""An ordered LiDAR sequence along a closed loop through a synthetic scene (for odometry).

The scene is in metres by construction: a ground plane (z = 0) and objects (the given
meshes, or built-in objects when none are given) rescaled to a few metres, set on the
ground on both sides of an elliptic loop. A spinning LiDAR at ``sensor_height_m`` drives
once around the loop, facing along the path, one scan every ``1 / rate_hz`` seconds.
Scans are instantaneous (no motion distortion to deskew).

Output folder::

    scan_000.ply ...        LiDAR frame (+x forward, +y left, +z up), float64
    ground_truth.json       mvreg.poses/1: {file: T_world_lidar}, timestamps, units "m"
    ground_truth_tum.txt    the same trajectory in TUM format (timestamp tx ty tz qx qy qz qw)
    timestamps.txt          one time per scan, seconds, in scan order
    synth.json              parameters, seed, scene objects and mesh hashes, point counts,
                            overlap of consecutive scans (and last -> first)
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from data_synth.builtin import builtin_object
from data_synth.meshes import MeshSource, load_mesh_with_source, mesh_diagonal, mesh_sha256
from data_synth.scanner import (
    LidarScanner,
    MeshRaycaster,
    NoiseModel,
    hit_fraction,
    rotate_rows,
    simulate_scan,
)
from data_synth.scans import (
    MAX_NOISE,
    _check_output,
    _prepare_output,
    scan_name,
    write_ply,
)
from mvreg.errors import ConfigError
from mvreg.geometry import make_transform
from mvreg.io.atomic import atomic_write_json, atomic_write_text
from mvreg.io.poses import write_poses_json, write_poses_tum

MAX_FRAMES = 100_000


@dataclass
class SceneObject:
    """One object placed in the scene.

    Attributes:
        name: source mesh name.
        sha256: hash of the source mesh (file bytes or arrays).
        diagonal_m: bounding-box diagonal after rescaling, metres.
        T_world_object: (4, 4) float64 pose of the rescaled, centred mesh.
    """

    name: str
    sha256: str
    diagonal_m: float
    T_world_object: np.ndarray


@dataclass
class Scene:
    """A scene mesh in metres and what it is made of.

    Attributes:
        mesh: all objects (and the ground) as one ``trimesh.Trimesh``, metres.
        objects: the placed objects, then the box buildings.
        loop_radii_m: (a, b) semi-axes of the elliptic path, metres.
        ground: whether a ground plane is included.
    """

    mesh: trimesh.Trimesh
    objects: list[SceneObject]
    loop_radii_m: tuple[float, float]
    ground: bool

    @property
    def object_size_m(self) -> float:
        """Mean diagonal of the mesh objects (not buildings), metres: what relative noise uses."""
        sizes = [o.diagonal_m for o in self.objects if o.name != "box"]
        return float(np.mean(sizes))


@dataclass
class SequenceResult:
    """What ``synthesize_sequence`` made.

    Attributes:
        out_dir: output folder.
        scan_paths: one path per scan, in time order.
        timestamps_s: (n,) float64 seconds.
        T_world_scan: {file name: (4, 4)} ground-truth LiDAR poses (world from LiDAR).
        consecutive_overlap: (n,) float64, overlap of scan i with scan (i + 1) mod n.
        point_counts: points per scan.
        config: the resolved parameters as written to ``synth.json``.
        scene: the scene the scans were cast in (metres).
    """

    out_dir: Path
    scan_paths: list[Path]
    timestamps_s: np.ndarray
    T_world_scan: dict[str, np.ndarray]
    consecutive_overlap: np.ndarray
    point_counts: list[int]
    config: dict = field(repr=False)
    scene: Scene | None = field(default=None, repr=False)

    def __repr__(self) -> str:
        return (
            f"SequenceResult(out_dir={str(self.out_dir)!r}, scans={len(self.scan_paths)}, "
            f"duration={float(self.timestamps_s[-1]) if len(self.timestamps_s) else 0.0:.2f} s, "
            f"min_consecutive_overlap={float(np.min(self.consecutive_overlap)):.2f})"
        )


def build_scene(
    meshes: Sequence | None = None,
    *,
    n_objects: int = 12,
    loop_radii_m: tuple[float, float] = (15.0, 10.0),
    object_size_m: tuple[float, float] = (2.0, 5.0),
    buildings: int = 10,
    ground: bool = True,
    seed: int = 0,
) -> Scene:
    """Objects set on the ground on both sides of an elliptic loop.

    Args:
        meshes: mesh paths / objects (anything :func:`data_synth.load_mesh` takes), used
            in turn; None: built-in objects with seeds 1, 2, ...
        n_objects: number of objects placed.
        loop_radii_m: semi-axes (a along x, b along y) of the path, metres.
        object_size_m: (min, max) object bounding-box diagonal after rescaling, metres.
        buildings: number of box buildings (4-10 m wide, 3-8 m tall) outside the loop.
        ground: add a ground plane at z = 0.
        seed: object sizes, yaws and positions.
    Returns:
        :class:`Scene` (metres).
    """
    a, b = loop_radii_m
    if not (0.0 < b <= a and np.isfinite(a)):
        raise ConfigError(f"loop radii must satisfy 0 < b <= a, not {loop_radii_m}")
    if n_objects < 1:
        raise ConfigError(f"the scene needs at least one object, not {n_objects}")
    if buildings < 0:
        raise ConfigError(f"buildings must be >= 0, not {buildings}")
    rng = np.random.default_rng([seed, 0x5CE4E])
    sources = _scene_sources(meshes, n_objects)
    path = _loop_positions(np.linspace(0.0, 2.0 * np.pi, 720, endpoint=False), a, b)
    parts, objects = [], []
    for i in range(n_objects):
        mesh, source = sources[i]
        size = rng.uniform(*object_size_m)
        yaw = rng.uniform(-np.pi, np.pi)
        R = _yaw_matrix(yaw)
        vertices = mesh.vertices - 0.5 * (mesh.bounds[0] + mesh.bounds[1])
        vertices = rotate_rows(R, vertices * (size / mesh_diagonal(mesh)))
        for _ in range(100):  # rejection: keep the object clear of the path
            s = 2.0 * np.pi * (i + rng.uniform(-0.3, 0.3)) / n_objects
            side = 1.0 if i % 2 == 0 else -1.0
            centre_xy = _loop_positions(np.array([s]), a, b)[0, :2] + side * rng.uniform(
                3.0, 6.0
            ) * _loop_outward_normal(s, a, b)
            clearance = np.min(np.linalg.norm(path[:, :2] - centre_xy, axis=1))
            if clearance >= 0.5 * size + 1.5:
                break
        else:
            raise ConfigError(f"could not place object {i} clear of the path; widen the loop")
        t = np.array([centre_xy[0], centre_xy[1], -vertices[:, 2].min()])
        parts.append(trimesh.Trimesh(vertices + t, mesh.faces, process=False))
        objects.append(SceneObject(source.name, source.sha256, float(size), make_transform(R, t)))
    for k in range(buildings):
        # Box "buildings" outside the loop, facing it: walls give odometry its structure.
        s = 2.0 * np.pi * (k + rng.uniform(-0.2, 0.2)) / buildings
        extents = np.array([rng.uniform(4.0, 10.0), rng.uniform(3.0, 6.0), rng.uniform(3.0, 8.0)])
        normal = _loop_outward_normal(s, a, b)
        centre_xy = _loop_positions(np.array([s]), a, b)[0, :2] + normal * (
            rng.uniform(9.0, 13.0) + 0.5 * extents[1]
        )
        R = _yaw_matrix(float(np.arctan2(normal[1], normal[0])) + 0.5 * np.pi)
        T = make_transform(R, np.array([centre_xy[0], centre_xy[1], 0.5 * extents[2]]))
        box = trimesh.creation.box(extents=extents, transform=T)
        parts.append(box)
        objects.append(SceneObject("box", mesh_sha256(box), float(np.linalg.norm(extents)), T))
    if ground:
        half = max(a, b) + 30.0
        corners = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]])
        parts.append(
            trimesh.Trimesh(corners.astype(np.float64), [[0, 1, 2], [0, 2, 3]], process=False)
        )
    scene_mesh = trimesh.util.concatenate(parts)
    return Scene(scene_mesh, objects, (float(a), float(b)), ground)


def synthesize_sequence(
    meshes: Sequence | None,
    out_dir: str | os.PathLike,
    *,
    frames: int = 100,
    rate_hz: float = 10.0,
    noise: float = 0.002,
    outliers: float = 0.0,
    dropout: float = 0.0,
    seed: int = 0,
    points_per_scan: int = 20_000,
    beams: int = 32,
    vertical_fov_deg: tuple[float, float] = (-25.0, 15.0),
    max_range_m: float = 60.0,
    sensor_height_m: float = 1.8,
    n_objects: int = 12,
    buildings: int = 10,
    loop_radii_m: tuple[float, float] = (15.0, 10.0),
    ground: bool = True,
    normals: bool = False,
    force: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> SequenceResult:
    """Drive a LiDAR once around a closed loop through a scene; write the scans in order.

    Args:
        meshes: scene objects (see :func:`build_scene`); None for built-in objects.
        out_dir: output folder (must be empty or absent unless ``force``).
        frames: number of scans over one loop.
        rate_hz: scan rate; scan k has timestamp k / rate_hz seconds.
        noise: range noise sigma as a fraction of the mean object diagonal.
        outliers, dropout: as in :func:`data_synth.synthesize_scans`.
        points_per_scan: wanted mean points per scan; sets the horizontal resolution
            (``beams`` stays fixed, as on a real sensor).
        beams, vertical_fov_deg, max_range_m: the LiDAR.
        sensor_height_m: LiDAR height above the ground.
        n_objects, buildings, loop_radii_m, ground: the scene (see :func:`build_scene`).
        normals: also write nx ny nz.
        force: replace the files of an earlier run.
        progress: called as ``progress(done, total)`` after each scan.
    Returns:
        :class:`SequenceResult`.
    """
    if not isinstance(frames, int | np.integer) or not 2 <= frames <= MAX_FRAMES:
        raise ConfigError(
            f"a sequence needs an integer number of frames in [2, {MAX_FRAMES}], not {frames}"
        )
    if not (np.isfinite(rate_hz) and rate_hz > 0.0):
        raise ConfigError(f"rate must be > 0 Hz, not {rate_hz}")
    if not (np.isfinite(noise) and 0.0 <= noise <= MAX_NOISE):
        raise ConfigError(f"noise must be in [0, {MAX_NOISE}], not {noise}")
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ConfigError(f"seed must be an integer >= 0, not {seed}")
    if not isinstance(points_per_scan, int | np.integer) or points_per_scan < 10:
        raise ConfigError(f"points per scan must be an integer >= 10, not {points_per_scan}")
    if not 0.0 < sensor_height_m:
        raise ConfigError(f"sensor height must be > 0 m, not {sensor_height_m}")
    out_dir = Path(out_dir)
    _check_output(out_dir, force)

    rng_scene, rng_scans = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    scene_seed = int(rng_scene.integers(2**31))
    scene = build_scene(
        meshes,
        n_objects=n_objects,
        buildings=buildings,
        loop_radii_m=loop_radii_m,
        ground=ground,
        seed=scene_seed,
    )
    timestamps_s = np.arange(frames) / rate_hz
    T_world_lidar = loop_poses(frames, scene.loop_radii_m, sensor_height_m)
    raycaster = MeshRaycaster(scene.mesh)
    lidar = _fit_sequence_lidar(
        raycaster, T_world_lidar, points_per_scan, beams, vertical_fov_deg, max_range_m, dropout
    )
    noise_model = NoiseModel(
        range_sigma=noise * scene.object_size_m, outliers=outliers, dropout=dropout
    )

    _prepare_output(out_dir)
    scan_seeds = np.random.SeedSequence(int(rng_scans.integers(2**63))).spawn(frames)
    paths, points_world, counts = [], [], []
    for k in range(frames):
        raw = simulate_scan(
            raycaster, lidar, T_world_lidar[k], noise_model, np.random.default_rng(scan_seeds[k])
        )
        path = out_dir / scan_name(k)
        write_ply(path, raw.points, raw.normals if normals else None)
        paths.append(path)
        counts.append(len(raw.points))
        points_world.append(
            rotate_rows(T_world_lidar[k][:3, :3], raw.points) + T_world_lidar[k][:3, 3]
        )
        if progress is not None:
            progress(k + 1, frames)
    tolerance_m = max(0.05, 4.0 * noise_model.range_sigma)
    consecutive = np.array(
        [
            covisibility(
                raycaster, lidar, T_world_lidar[(k + 1) % frames], points_world[k], tolerance_m
            )
            for k in range(frames)
        ]
    )

    names = [p.name for p in paths]
    poses = dict(zip(names, T_world_lidar, strict=True))
    write_poses_json(
        out_dir / "ground_truth.json",
        poses,
        object_diagonal=scene.object_size_m,
        units="m",
        world_frame="scene frame: ground plane z = 0, loop centred on the origin",
        timestamps=timestamps_s,
    )
    write_poses_tum(out_dir / "ground_truth_tum.txt", list(T_world_lidar), timestamps_s)
    atomic_write_text(
        out_dir / "timestamps.txt", "".join(f"{t!r}\n" for t in timestamps_s.tolist())
    )
    config = {
        "format": "mvreg.synth/1",
        "mode": "sequence",
        "seed": int(seed),
        "units": "m",
        "parameters": {
            "frames": frames,
            "rate_hz": rate_hz,
            "noise": noise,
            "noise_sigma_m": noise_model.range_sigma,
            "outliers": outliers,
            "dropout": dropout,
            "points_per_scan": points_per_scan,
            "sensor_height_m": sensor_height_m,
            "loop_radii_m": list(scene.loop_radii_m),
            "n_objects": n_objects,
            "buildings": buildings,
            "ground": ground,
            "normals": normals,
            "scanner": lidar.describe(),
        },
        "scene": {
            "seed": scene_seed,
            "object_size_m": scene.object_size_m,
            "objects": [
                {
                    "name": o.name,
                    "sha256": o.sha256,
                    "diagonal_m": o.diagonal_m,
                    "T_world_object": o.T_world_object,
                }
                for o in scene.objects
            ],
        },
        "point_counts": counts,
        "consecutive_overlap": {
            "definition": "fraction of scan i's points that scan (i + 1) mod n also sees "
            "(in its field of view and range, not occluded)",
            "tolerance_m": tolerance_m,
            "values": consecutive,
        },
    }
    atomic_write_json(out_dir / "synth.json", config)
    return SequenceResult(out_dir, paths, timestamps_s, poses, consecutive, counts, config, scene)


def loop_poses(
    frames: int, loop_radii_m: tuple[float, float], sensor_height_m: float
) -> np.ndarray:
    """(frames, 4, 4) LiDAR poses evenly spaced in angle around the ellipse, facing along it."""
    a, b = loop_radii_m
    s = 2.0 * np.pi * np.arange(frames) / frames
    positions = _loop_positions(s, a, b)
    positions[:, 2] = sensor_height_m
    yaw = np.arctan2(b * np.cos(s), -a * np.sin(s))  # direction of d/ds (a cos s, b sin s)
    return np.stack(
        [make_transform(_yaw_matrix(y), p) for y, p in zip(yaw, positions, strict=True)]
    )


def covisibility(
    raycaster: MeshRaycaster,
    lidar: LidarScanner,
    T_world_lidar: np.ndarray,
    points_world: np.ndarray,
    tolerance: float,
) -> float:
    """Fraction of ``points_world`` that a LiDAR at ``T_world_lidar`` would also see.

    A point counts when it lies within the LiDAR's range and vertical field of view and
    the ray towards it first hits the scene within ``tolerance`` of it. (Nearest-neighbour
    overlap says little for LiDAR: its rings sample the ground at ranges that move with
    the sensor.)

    Args:
        points_world: (N, 3) float64, world frame.
        tolerance: metres.
    """
    if len(points_world) == 0:
        return 0.0
    origin = T_world_lidar[:3, 3]
    offsets = points_world - origin
    ranges = np.linalg.norm(offsets, axis=1)
    directions = offsets / np.maximum(ranges, 1e-12)[:, None]
    local = rotate_rows(T_world_lidar[:3, :3].T, directions)
    elevation = np.degrees(np.arcsin(np.clip(local[:, 2], -1.0, 1.0)))
    lo, hi = lidar.vertical_fov_deg
    in_view = (
        (elevation >= lo)
        & (elevation <= hi)
        & (ranges > lidar.min_range)
        & (ranges <= lidar.max_range)
    )
    hit_ranges, _ = raycaster.cast(origin, directions)
    seen = in_view & (np.abs(hit_ranges - ranges) <= tolerance)
    return float(np.mean(seen))


def _fit_sequence_lidar(raycaster, poses, points_per_scan, beams, vfov, max_range, dropout):
    """Horizontal steps so that the mean scan has ~``points_per_scan`` points."""
    probe = LidarScanner(beams, 512, tuple(vfov), max_range=max_range, min_range=0.5)
    sample = poses[:: max(1, len(poses) // 8)]
    fraction = max(float(np.mean([hit_fraction(raycaster, probe, T) for T in sample])), 1e-3)
    steps = int(round(points_per_scan / (beams * fraction * (1.0 - dropout))))
    return LidarScanner(beams, max(steps, 16), tuple(vfov), max_range=max_range, min_range=0.5)


def _scene_sources(meshes, n_objects) -> list[tuple[trimesh.Trimesh, MeshSource]]:
    if not meshes:
        out = []
        for i in range(n_objects):
            mesh = builtin_object(seed=i + 1, subdivisions=4)
            out.append((mesh, MeshSource(f"builtin:{i + 1}", mesh_sha256(mesh), "unitless")))
        return out
    loaded = [load_mesh_with_source(m) for m in meshes]
    return [loaded[i % len(loaded)] for i in range(n_objects)]


def _loop_positions(s: np.ndarray, a: float, b: float) -> np.ndarray:
    return np.column_stack([a * np.cos(s), b * np.sin(s), np.zeros_like(s)])


def _loop_outward_normal(s: float, a: float, b: float) -> np.ndarray:
    n = np.array([b * np.cos(s), a * np.sin(s)])
    return n / np.linalg.norm(n)


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
