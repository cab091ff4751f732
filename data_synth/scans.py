"""Synthesize a set of partial scans of one mesh with ground-truth poses.

``synthesize_scans`` reads like its table of contents: check parameters -> load mesh ->
check the output folder -> place views -> fit the scanner -> cast scans -> overlap ->
write scans, ``ground_truth.json`` and ``synth.json``. ``generate_scans`` is the same
without files, for tests and callers who want arrays.

Output folder::

    scan_000.ply ...      binary little-endian PLY, float64 x y z (optional nx ny nz)
    ground_truth.json     mvreg.poses/1: {file: T_world_scan 4x4}, object_diagonal, units
    synth.json            every parameter, seed, mesh sha256, point counts, overlap matrix

The world frame is the mesh's own frame. Each scan is stored in its sensor frame
(``T_world_scan = T_world_sensor``) unless ``random_frames``, which stores it in a random
frame (uniform rotation, translation ~ one object diagonal) and records that pose
instead. Same inputs and seed give byte-identical files.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from data_synth.meshes import MeshSource, load_mesh_with_source, mesh_diagonal
from data_synth.placement import PLACEMENTS, make_viewpoints
from data_synth.scanner import (
    LidarScanner,
    MeshRaycaster,
    NoiseModel,
    PinholeScanner,
    Scanner,
    fit_lidar,
    fit_pinhole,
    rotate_rows,
    simulate_scan,
)
from mvreg.errors import ConfigError, InputError, OutputExistsError
from mvreg.geometry import invert_transform, make_transform, random_rotations
from mvreg.io.atomic import atomic_write_bytes, atomic_write_json
from mvreg.io.poses import write_poses_json

SYNTH_FORMAT = "mvreg.synth/1"
SCANNERS = ("pinhole", "lidar")
#: Files a synthesis writes besides ``scan_*.ply``; ``force`` replaces exactly these.
METADATA_FILES = ("ground_truth.json", "synth.json", "timestamps.txt", "ground_truth_tum.txt")
MAX_VIEWS = 10_000
MAX_POINTS_PER_SCAN = 20_000_000
MAX_NOISE = 0.1


@dataclass
class SynthScan:
    """One synthesized scan.

    Attributes:
        name: file name, ``scan_000.ply`` ...
        points: (N, 3) float64 in the scan's stored frame.
        normals: (N, 3) float64 unit normals in the same frame (facing the sensor).
        is_outlier: (N,) bool.
        T_world_scan: (4, 4) float64, world from the stored frame (the ground truth).
        T_world_sensor: (4, 4) float64, world from the sensor frame.
    """

    name: str
    points: np.ndarray
    normals: np.ndarray
    is_outlier: np.ndarray
    T_world_scan: np.ndarray
    T_world_sensor: np.ndarray
    n_rays: int = 0

    def points_world(self) -> np.ndarray:
        """(N, 3) float64 points in the world (mesh) frame."""
        return rotate_rows(self.T_world_scan[:3, :3], self.points) + self.T_world_scan[:3, 3]


@dataclass
class SynthResult:
    """What ``synthesize_scans`` made.

    Attributes:
        out_dir: output folder.
        scan_paths: one path per scan, in order.
        T_world_scan: {file name: (4, 4) float64} ground truth (world from stored frame).
        overlap: (n, n) float64, ``overlap[i, j]`` = fraction of scan i's points within
            ``overlap_distance`` of scan j in the true frame (diagonal = 1).
        overlap_distance: mesh units.
        point_counts: points per scan.
        object_diagonal: mesh bounding-box diagonal, mesh units.
        units: mesh units if known, else ``"unknown"``.
        config: the resolved parameters as written to ``synth.json``.
        scans: the scans themselves (arrays), in order.
    """

    out_dir: Path
    scan_paths: list[Path]
    T_world_scan: dict[str, np.ndarray]
    overlap: np.ndarray
    overlap_distance: float
    point_counts: list[int]
    object_diagonal: float
    units: str
    config: dict = field(repr=False)
    scans: list[SynthScan] = field(repr=False, default_factory=list)

    @property
    def ground_truth_path(self) -> Path:
        return self.out_dir / "ground_truth.json"

    @property
    def synth_path(self) -> Path:
        return self.out_dir / "synth.json"

    def __repr__(self) -> str:
        n = len(self.scan_paths)
        off = self.overlap[~np.eye(n, dtype=bool)] if n > 1 else np.zeros(1)
        return (
            f"SynthResult(out_dir={str(self.out_dir)!r}, scans={n}, "
            f"points={min(self.point_counts, default=0)}..{max(self.point_counts, default=0)}, "
            f"diagonal={self.object_diagonal:.4g} {self.units}, "
            f"max_overlap={float(off.max()):.2f})"
        )


def synthesize_scans(
    mesh_or_path,
    out_dir: str | os.PathLike,
    *,
    views: int = 12,
    placement: str = "sphere",
    noise: float = 0.002,
    outliers: float = 0.0,
    dropout: float = 0.0,
    seed: int = 0,
    scanner: str | Scanner = "pinhole",
    points_per_scan: int = 20_000,
    random_frames: bool = False,
    force: bool = False,
    distance: float = 1.5,
    normals: bool = False,
    viewpoints: np.ndarray | None = None,
    elevation_deg: float = 20.0,
    axis: Sequence[float] = (0.0, 0.0, 1.0),
    max_incidence_deg: float = 85.0,
    units: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SynthResult:
    """Synthesize ``views`` partial scans of a mesh and write them with their ground truth.

    Args:
        mesh_or_path: mesh file path, ``"builtin"`` / ``"builtin:SEED"``, or a mesh object
            (see :func:`data_synth.load_mesh`).
        out_dir: output folder (created; must be empty or absent unless ``force``).
        views: number of scans (ignored when ``viewpoints`` are given).
        placement: ``sphere``, ``turntable``, ``random`` or ``explicit``.
        noise: range noise sigma as a fraction of the object diagonal (0.002 = 0.2%).
        outliers: fraction of each scan's points turned into outliers, [0, 1).
        dropout: probability of losing each point, [0, 1).
        seed: seeds placement (random), noise, dropout, outliers and random frames.
        scanner: ``"pinhole"``, ``"lidar"`` (both fitted to the object and to
            ``points_per_scan``) or a ready ``PinholeScanner`` / ``LidarScanner``.
        points_per_scan: wanted mean number of points per scan (approximate).
        random_frames: store each scan in a random frame instead of its sensor frame.
        force: replace the ``scan_*.ply`` and metadata files of an earlier run.
        distance: sensor distance from the object centre, in object diagonals.
        normals: also write nx ny nz (sensor-facing surface normals).
        viewpoints: (N, 3) absolute sensor positions (mesh units) for ``explicit``.
        elevation_deg: turntable elevation, degrees.
        axis: (3,) up direction (turntable axis, up hint of every view).
        max_incidence_deg: hits more grazing than this are lost.
        units: override the units written to ``ground_truth.json``.
        progress: called as ``progress(done, total)`` after each scan is simulated.
    Returns:
        :class:`SynthResult`.
    Raises:
        MeshError: the mesh cannot be loaded. ConfigError: an absurd parameter.
        OutputExistsError: ``out_dir`` is not empty and ``force`` is False.
    """
    _check_parameters(views, placement, noise, seed, points_per_scan, viewpoints)
    mesh, source = load_mesh_with_source(mesh_or_path)
    out_dir = Path(out_dir)
    _check_output(out_dir, force)
    scans, config = generate_scans(
        mesh,
        views=views,
        placement=placement,
        noise=noise,
        outliers=outliers,
        dropout=dropout,
        seed=seed,
        scanner=scanner,
        points_per_scan=points_per_scan,
        random_frames=random_frames,
        distance=distance,
        viewpoints=viewpoints,
        elevation_deg=elevation_deg,
        axis=axis,
        max_incidence_deg=max_incidence_deg,
        progress=progress,
    )
    diagonal = mesh_diagonal(mesh)
    overlap, overlap_distance = _overlap_for(scans, diagonal, noise * diagonal)
    units = units or source.units

    _prepare_output(out_dir)
    paths = []
    for scan in scans:
        path = out_dir / scan.name
        write_ply(path, scan.points, scan.normals if normals else None)
        paths.append(path)
    T_world_scan = {s.name: s.T_world_scan for s in scans}
    write_poses_json(
        out_dir / "ground_truth.json",
        T_world_scan,
        object_diagonal=diagonal,
        units=units,
        world_frame=f"mesh frame of {source.name}",
        mesh=source.name,
    )
    config = _synth_json(
        config, source, mesh, units, normals, scans, overlap, overlap_distance, seed
    )
    atomic_write_json(out_dir / "synth.json", config)
    return SynthResult(
        out_dir=out_dir,
        scan_paths=paths,
        T_world_scan=T_world_scan,
        overlap=overlap,
        overlap_distance=overlap_distance,
        point_counts=[len(s.points) for s in scans],
        object_diagonal=diagonal,
        units=units,
        config=config,
        scans=scans,
    )


def generate_scans(
    mesh: trimesh.Trimesh,
    *,
    views: int = 12,
    placement: str = "sphere",
    noise: float = 0.002,
    outliers: float = 0.0,
    dropout: float = 0.0,
    seed: int = 0,
    scanner: str | Scanner = "pinhole",
    points_per_scan: int = 20_000,
    random_frames: bool = False,
    distance: float = 1.5,
    viewpoints: np.ndarray | None = None,
    elevation_deg: float = 20.0,
    axis: Sequence[float] = (0.0, 0.0, 1.0),
    max_incidence_deg: float = 85.0,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[list[SynthScan], dict]:
    """Simulate the scans in memory (same parameters as :func:`synthesize_scans`).

    Returns:
        the scans, and a dict of the resolved parameters (scanner, viewpoints, noise sigma).
    """
    _check_parameters(views, placement, noise, seed, points_per_scan, viewpoints)
    scanner_kind = scanner if isinstance(scanner, str) else scanner.kind
    rng_views, rng_frames, rng_scans = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3)
    )
    diagonal = mesh_diagonal(mesh)
    lo, hi = mesh.bounds
    centre = 0.5 * (lo + hi)
    noise_model = NoiseModel(
        range_sigma=noise * diagonal,
        outliers=outliers,
        dropout=dropout,
        max_incidence_deg=max_incidence_deg,
    )
    vp = make_viewpoints(
        "explicit" if viewpoints is not None else placement,
        views,
        centre,
        diagonal,
        distance=distance,
        scanner=scanner_kind,
        rng=rng_views,
        elevation_deg=elevation_deg,
        axis=axis,
        positions=viewpoints,
    )
    raycaster = MeshRaycaster(mesh)
    sensor = _resolve_scanner(
        scanner, raycaster, vp.T_world_sensor, centre, diagonal, points_per_scan, dropout
    )

    n = len(vp)
    if random_frames:
        R = random_rotations(rng_frames, n, 3)
        t = centre + diagonal * rng_frames.standard_normal((n, 3))
        T_world_local = [make_transform(R[i], t[i]) for i in range(n)]
    scan_seeds = np.random.SeedSequence(int(rng_scans.integers(2**63))).spawn(n)
    scans = []
    for i in range(n):
        T_world_sensor = vp.T_world_sensor[i]
        raw = simulate_scan(
            raycaster, sensor, T_world_sensor, noise_model, np.random.default_rng(scan_seeds[i])
        )
        points, normals, T_world_scan = raw.points, raw.normals, T_world_sensor
        if random_frames:
            T_world_scan = T_world_local[i]
            T_scan_sensor = invert_transform(T_world_scan) @ T_world_sensor
            points = rotate_rows(T_scan_sensor[:3, :3], points) + T_scan_sensor[:3, 3]
            normals = rotate_rows(T_scan_sensor[:3, :3], normals)
        scans.append(
            SynthScan(
                name=scan_name(i),
                points=points,
                normals=normals,
                is_outlier=raw.is_outlier,
                T_world_scan=T_world_scan,
                T_world_sensor=T_world_sensor,
                n_rays=raw.n_rays,
            )
        )
        if progress is not None:
            progress(i + 1, n)
    config = {
        "placement": vp.placement,
        "views": n,
        "distance_diagonals": distance,
        "elevation_deg": elevation_deg if vp.placement == "turntable" else None,
        "axis": [float(a) for a in axis],
        "noise": noise,
        "noise_sigma": noise_model.range_sigma,
        "outliers": outliers,
        "dropout": dropout,
        "max_incidence_deg": max_incidence_deg,
        "points_per_scan": points_per_scan,
        "random_frames": random_frames,
        "scanner": sensor.describe(),
        "viewpoints": vp.positions,
    }
    return scans, config


def scan_name(index: int) -> str:
    """``scan_000.ply`` style file name (at least three digits)."""
    return f"scan_{index:03d}.ply"


def overlap_matrix(
    points_world: Sequence[np.ndarray], distance: float, max_queries: int = 5000
) -> np.ndarray:
    """Pairwise overlap of scans already in a common frame.

    Args:
        points_world: n arrays (N_i, 3) float64.
        distance: a point of scan i overlaps scan j when scan j has a point this close.
        max_queries: fractions are estimated on every k-th point of scan i, k chosen so
            that at most ~``max_queries`` points are queried (all points when fewer).
    Returns:
        (n, n) float64; ``[i, j]`` = fraction of scan i's points that overlap scan j
        (1 on the diagonal, 0 for an empty scan i).
    """
    n = len(points_world)
    trees = [cKDTree(p) if len(p) else None for p in points_world]
    # A strided subset estimates each fraction to ~1% at a fraction of the cost.
    queries = [p[:: max(1, len(p) // max_queries)] for p in points_world]
    out = np.eye(n)
    for i in range(n):
        for j in range(n):
            if i == j or trees[j] is None or len(queries[i]) == 0:
                continue
            d, _ = trees[j].query(queries[i], k=1, distance_upper_bound=distance)
            out[i, j] = float(np.mean(np.isfinite(d)))
    return out


def ply_bytes(points: np.ndarray, normals: np.ndarray | None = None) -> bytes:
    """Binary little-endian PLY of (N, 3) float64 points and optional (N, 3) normals."""
    points = np.asarray(points, dtype="<f8")
    names = ["x", "y", "z"]
    columns = [points]
    if normals is not None:
        names += ["nx", "ny", "nz"]
        columns.append(np.asarray(normals, dtype="<f8"))
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment mvreg data_synth",
        f"element vertex {len(points)}",
        *(f"property double {name}" for name in names),
        "end_header",
    ]
    body = np.ascontiguousarray(np.hstack(columns), dtype="<f8").tobytes()
    return ("\n".join(header) + "\n").encode("ascii") + body


def write_ply(path: str | os.PathLike, points: np.ndarray, normals: np.ndarray | None = None):
    """Write :func:`ply_bytes` atomically."""
    atomic_write_bytes(path, ply_bytes(points, normals))


def _check_parameters(views, placement, noise, seed, points_per_scan, viewpoints) -> None:
    if viewpoints is None:
        if not isinstance(views, int | np.integer) or not 1 <= views <= MAX_VIEWS:
            raise ConfigError(f"views must be an integer in [1, {MAX_VIEWS}], not {views}")
        if placement not in PLACEMENTS:
            raise ConfigError(
                f"unknown placement {placement!r}; choose one of {', '.join(PLACEMENTS)}"
            )
        if placement == "explicit":
            raise ConfigError("explicit placement needs viewpoint positions")
    if not (np.isfinite(noise) and 0.0 <= noise <= MAX_NOISE):
        raise ConfigError(
            f"noise must be in [0, {MAX_NOISE}] (a fraction of the object diagonal), not {noise}"
        )
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ConfigError(f"seed must be an integer >= 0, not {seed}")
    if not isinstance(points_per_scan, int | np.integer) or not (
        10 <= points_per_scan <= MAX_POINTS_PER_SCAN
    ):
        raise ConfigError(
            f"points per scan must be an integer in [10, {MAX_POINTS_PER_SCAN}], "
            f"not {points_per_scan}"
        )


def _resolve_scanner(
    scanner, raycaster, T_world_sensors, centre, diagonal, points_per_scan, dropout
):
    if isinstance(scanner, PinholeScanner | LidarScanner):
        return scanner
    if scanner not in SCANNERS:
        raise ConfigError(f"unknown scanner {scanner!r}; choose pinhole or lidar")
    fit = fit_pinhole if scanner == "pinhole" else fit_lidar
    return fit(
        raycaster,
        list(T_world_sensors),
        centre,
        0.5 * diagonal,
        points_per_scan,
        keep_fraction=1.0 - dropout,
    )


def _check_output(out_dir: Path, force: bool) -> None:
    """Refuse a file, or a non-empty folder without ``force`` (before any work is done)."""
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not force:
        raise OutputExistsError(
            f"{out_dir}: folder is not empty; use --force (force=True) to replace its scans"
        )


def _prepare_output(out_dir: Path) -> None:
    """Create the folder; remove the scans and metadata files of an earlier run."""
    # Stale scans of a larger earlier run would be picked up by a registration.
    if out_dir.is_dir():
        for old in out_dir.glob("scan_*.ply"):
            old.unlink()
        for name in METADATA_FILES:
            (out_dir / name).unlink(missing_ok=True)
    out_dir.mkdir(parents=True, exist_ok=True)


def _overlap_for(scans: list[SynthScan], diagonal: float, sigma: float) -> tuple[np.ndarray, float]:
    """Overlap matrix with distance max(1% diagonal, 2x median point spacing, 3 sigma)."""
    points = [s.points_world() for s in scans]
    spacings = []
    for p in points:
        if len(p) >= 2:
            d, _ = cKDTree(p).query(p, k=2)
            spacings.append(float(np.median(d[:, 1])))
    spacing = float(np.median(spacings)) if spacings else 0.0
    distance = max(0.01 * diagonal, 2.0 * spacing, 3.0 * sigma)
    return overlap_matrix(points, distance), distance


def _synth_json(config, source: MeshSource, mesh, units, normals, scans, overlap, distance, seed):
    import open3d

    lo, hi = mesh.bounds
    return {
        "format": SYNTH_FORMAT,
        "seed": int(seed),
        "mesh": {
            "name": source.name,
            "sha256": source.sha256,
            "units": units,
            "vertices": len(mesh.vertices),
            "faces": len(mesh.faces),
            "bbox_min": lo,
            "bbox_max": hi,
            "diagonal": mesh_diagonal(mesh),
        },
        "parameters": {**config, "normals": normals},
        "scans": [
            {
                "file": s.name,
                "points": len(s.points),
                "outliers": int(np.sum(s.is_outlier)),
                "rays": s.n_rays,
                "T_world_sensor": s.T_world_sensor,
            }
            for s in scans
        ],
        "point_counts": [len(s.points) for s in scans],
        "overlap": {
            "definition": "fraction of scan i's points within distance of scan j, true frame",
            "distance": distance,
            "matrix": overlap,
        },
        "versions": {"numpy": np.__version__, "open3d": open3d.__version__},
    }


def read_synth_json(path: str | os.PathLike) -> dict:
    """Read a ``synth.json`` (raises InputError if it is not one)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{path}: not a readable synth.json ({e})") from None
    if data.get("format") != SYNTH_FORMAT:
        raise InputError(f"{path}: not a {SYNTH_FORMAT} file")
    return data
