"""``mvreg synth``: synthetic partial scans of a mesh (the library is :mod:`data_synth`).
Registered by :mod:`mvreg.cli` as ``app.command("synth")(synth_command)``.

Heavy imports (open3d, trimesh) happen inside the command so ``mvreg --help`` stays fast.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer


class PlacementChoice(str, Enum):
    sphere = "sphere"
    turntable = "turntable"
    random = "random"
    explicit = "explicit"


class ScannerChoice(str, Enum):
    pinhole = "pinhole"
    lidar = "lidar"


def synth_command(
    mesh: Annotated[
        str,
        typer.Argument(
            metavar="MESH|builtin",
            help="Mesh file trimesh reads (OBJ, PLY, STL, OFF, GLB), or 'builtin' / "
            "'builtin:SEED' for the procedural asymmetric object.",
            show_default=False,
        ),
    ],
    out: Annotated[
        Path,
        typer.Option(
            "--out", "-o", help="Output folder (scan_000.ply ..., ground_truth.json, synth.json)."
        ),
    ],
    views: Annotated[
        int | None,
        typer.Option(
            help="Number of scans. (default: 12; 100 frames with --sequence)", show_default=False
        ),
    ] = None,
    placement: Annotated[
        PlacementChoice,
        typer.Option(case_sensitive=False, help="How views are spread around the object."),
    ] = PlacementChoice.sphere,
    noise: Annotated[
        float,
        typer.Option(help="Range noise sigma along the ray, as a fraction of the object diagonal."),
    ] = 0.002,
    outliers: Annotated[
        float, typer.Option(help="Fraction of each scan's points made outliers.")
    ] = 0.0,
    dropout: Annotated[float, typer.Option(help="Probability that a point is lost.")] = 0.0,
    seed: Annotated[int, typer.Option(help="Random seed: same seed, same bytes.")] = 0,
    scanner: Annotated[
        ScannerChoice | None,
        typer.Option(
            case_sensitive=False,
            help="Sensor model. (default: pinhole; lidar with --sequence)",
            show_default=False,
        ),
    ] = None,
    points_per_scan: Annotated[
        int, typer.Option(help="Wanted mean number of points per scan (approximate).")
    ] = 20_000,
    distance: Annotated[
        float, typer.Option(help="Sensor distance from the object centre, in object diagonals.")
    ] = 1.5,
    elevation: Annotated[
        float, typer.Option(help="Turntable elevation of the ring, degrees.")
    ] = 20.0,
    viewpoints: Annotated[
        Path | None,
        typer.Option(
            help="Text file of sensor positions, one 'x y z' per line (mesh units); implies "
            "--placement explicit.",
            show_default=False,
        ),
    ] = None,
    random_frames: Annotated[
        bool,
        typer.Option(
            "--random-frames", help="Store each scan in a random frame, not its sensor frame."
        ),
    ] = False,
    normals: Annotated[bool, typer.Option("--normals", help="Also write nx ny nz.")] = False,
    sequence: Annotated[
        bool,
        typer.Option(
            "--sequence",
            help="Ordered LiDAR sequence along a closed loop through a scene of objects "
            "(MESH, or built-in objects for 'builtin') with timestamps, for odometry.",
        ),
    ] = False,
    rate_hz: Annotated[float, typer.Option(help="Scan rate of --sequence, Hz.")] = 10.0,
    force: Annotated[
        bool,
        typer.Option("--force", help="Replace the scans of an earlier run in a non-empty --out."),
    ] = False,
):
    """Synthesize partial scans of a mesh, with ground-truth poses.

    Ray-casts a range camera or a spinning LiDAR (first hit only, so
    self-occlusion is real), adds range noise along the ray, outliers
    and dropout, and writes each scan in its sensor frame; the true
    poses go to ground_truth.json, every parameter to synth.json.

    Examples:
      mvreg synth builtin --out scans/ --views 12
      mvreg synth bunny.obj --out bunny/ --noise 0.001 --scanner lidar
      mvreg synth builtin --out odo/ --sequence --views 200
    """
    from mvreg.errors import MvregError

    try:
        if sequence:
            result = _run_sequence(
                mesh, out, views, noise, outliers, dropout, seed, scanner, points_per_scan,
                random_frames, normals, rate_hz, force,
            )  # fmt: skip
            typer.echo(
                f"wrote {len(result.scan_paths)} LiDAR scans over {result.timestamps_s[-1]:.1f} s "
                f"({min(result.point_counts)}-{max(result.point_counts)} points) to {out}"
            )
        else:
            result = _run_scans(
                mesh, out, views, placement, noise, outliers, dropout, seed, scanner,
                points_per_scan, distance, elevation, viewpoints, random_frames, normals, force,
            )  # fmt: skip
            typer.echo(
                f"wrote {len(result.scan_paths)} scans ({min(result.point_counts)}-"
                f"{max(result.point_counts)} points, object diagonal "
                f"{result.object_diagonal:.4g} {result.units}) to {out}"
            )
    except MvregError as e:
        typer.echo(f"mvreg: error: {e}", err=True)
        raise typer.Exit(e.exit_code) from None


def _run_scans(
    mesh, out, views, placement, noise, outliers, dropout, seed, scanner, points_per_scan,
    distance, elevation, viewpoints, random_frames, normals, force,
):  # fmt: skip
    from data_synth.scans import synthesize_scans

    positions = _read_viewpoints(viewpoints) if viewpoints is not None else None
    if placement == PlacementChoice.explicit and positions is None:
        from mvreg.errors import ConfigError

        raise ConfigError("--placement explicit needs --viewpoints FILE")
    n_views = 12 if views is None else views
    with _ProgressBar("scanning") as bar:
        return synthesize_scans(
            mesh,
            out,
            views=n_views if positions is None else len(positions),
            placement=placement.value,
            noise=noise,
            outliers=outliers,
            dropout=dropout,
            seed=seed,
            scanner=(scanner or ScannerChoice.pinhole).value,
            points_per_scan=points_per_scan,
            random_frames=random_frames,
            force=force,
            distance=distance,
            normals=normals,
            viewpoints=positions,
            elevation_deg=elevation,
            progress=bar.update,
        )


def _run_sequence(
    mesh, out, views, noise, outliers, dropout, seed, scanner, points_per_scan,
    random_frames, normals, rate_hz, force,
):  # fmt: skip
    from data_synth.meshes import BUILTIN_NAME
    from data_synth.sequence import synthesize_sequence
    from mvreg.errors import ConfigError

    if scanner == ScannerChoice.pinhole:
        raise ConfigError("--sequence simulates a spinning LiDAR; drop --scanner pinhole")
    if random_frames:
        raise ConfigError(
            "--random-frames does not apply to --sequence (scans stay in LiDAR frames)"
        )
    meshes = None if mesh == BUILTIN_NAME else [mesh]
    with _ProgressBar("scanning") as bar:
        return synthesize_sequence(
            meshes,
            out,
            frames=100 if views is None else views,
            rate_hz=rate_hz,
            noise=noise,
            outliers=outliers,
            dropout=dropout,
            seed=seed,
            points_per_scan=points_per_scan,
            normals=normals,
            force=force,
            progress=bar.update,
        )


def _read_viewpoints(path: Path):
    """(N, 3) float64 positions from a text file of 'x y z' lines."""
    import warnings

    import numpy as np

    from mvreg.errors import InputError

    try:
        with warnings.catch_warnings():  # an empty file: refused below, without numpy's word
            warnings.simplefilter("ignore", UserWarning)
            positions = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: not a text file of 'x y z' lines ({e})") from None
    if positions.ndim != 2 or positions.shape[1] != 3 or len(positions) == 0:
        raise InputError(
            f"{path}: expected one 'x y z' line per viewpoint, got shape {positions.shape}"
        )
    return positions


class _ProgressBar:
    """A rich progress bar advanced by ``update(done, total)`` callbacks."""

    def __init__(self, description: str):
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
        )

        self._progress = Progress(
            TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()
        )
        self._description = description
        self._task = None

    def __enter__(self):
        self._progress.start()
        return self

    def __exit__(self, *exc):
        self._progress.stop()
        return False

    def update(self, done: int, total: int) -> None:
        if self._task is None:
            self._task = self._progress.add_task(self._description, total=total)
        self._progress.update(self._task, completed=done, total=total)
