"""Rerun recording of a registration run: one class, and a no-op stand-in when it is off.

`make_recorder` is the only place that decides where the data goes (an ``.rrd`` file,
a spawned viewer, both, or nowhere). Everything logged here is static except the
solver scalars, which live on the ``solver_iteration`` timeline.

Entity layout (names are escaped entity-path parts, e.g. ``bun000.ply``):

- ``config``                          resolved configuration (markdown text)
- ``raw/<name>``                      raw scans as loaded, colored per scan
- ``world/scans/<name>``              ``T_world_scan`` as a transform, with axes
- ``world/scans/<name>/points``       the scan in its own frame, colored per scan
- ``world/pairs/<a>--<b>``            correspondences of a pair as line segments
- ``world/ground_truth/<name>``       ground-truth pose (axes), optional points
- ``solver/objective`` ...            scalars on the ``solver_iteration`` timeline
- ``residual_heatmap/merged``         merged cloud colored by residual (viridis)
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType

import numpy as np

from mvreg.viz.colors import residual_colors, scan_colors

logger = logging.getLogger(__name__)

SOLVER_TIMELINE = "solver_iteration"
SOLVER_SCALARS = ("objective", "primal_residual", "dual_residual", "rho")
DEFAULT_VIEWER_PORT = 9876


class NullRecorder:
    """Stands in for `Recorder` when recording is off: accepts every call, does nothing.

    Attributes:
        warnings: why a requested output (viewer, file) is not produced, for the CLI.
    """

    rrd_path: Path | None = None

    def __init__(self, warnings: Sequence[str] = ()) -> None:
        self.warnings = list(warnings)

    @property
    def enabled(self) -> bool:
        return False

    def log_config(self, config: Mapping | str) -> None:
        """Log the resolved configuration (a mapping rendered as JSON, or text)."""

    def log_raw_scans(self, names: Sequence[str], points_list: Sequence[np.ndarray]) -> None:
        """Log raw scans as loaded: ``points_list[i]`` is ``(N_i, 3)``."""

    def log_solver_iteration(
        self,
        step: int,
        objective: float | None = None,
        primal_residual: float | None = None,
        dual_residual: float | None = None,
        rho: float | None = None,
    ) -> None:
        """Log one solver iteration's scalars at ``solver_iteration = step``."""

    def log_aligned(
        self,
        names: Sequence[str],
        points_list: Sequence[np.ndarray],
        T_world_scan: Sequence[np.ndarray],
    ) -> None:
        """Log aligned scans: ``(N_i, 3)`` points in the scan frame and ``(4, 4)`` poses."""

    def log_pair_correspondences(
        self,
        name_a: str,
        name_b: str,
        points_a_world: np.ndarray,
        points_b_world: np.ndarray,
        weight: float | None = None,
    ) -> None:
        """Log matched points of one pair, both ``(K, 3)`` in the world frame."""

    def log_residual_heatmap(
        self, points_world: np.ndarray, residuals: np.ndarray, clip_percentile: float = 95.0
    ) -> None:
        """Log a merged ``(N, 3)`` cloud colored by its ``(N,)`` residuals."""

    def log_ground_truth(
        self,
        names: Sequence[str],
        T_world_scan_true: Sequence[np.ndarray],
        points_list: Sequence[np.ndarray] | None = None,
    ) -> None:
        """Log ground-truth ``(4, 4)`` poses, already expressed in the recording's world."""

    def close(self) -> None:
        """Finish the recording."""

    def abort(self) -> None:
        """Drop the recording without producing a file."""

    def __enter__(self):
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(warnings={self.warnings!r})"


class Recorder(NullRecorder):
    """Writes a registration run to a rerun recording stream.

    Build it with `make_recorder`, which chooses the sinks. The ``.rrd`` is written to a
    temporary file beside ``rrd_path`` and renamed onto it by `close`, so an interrupted
    run never leaves a half-written recording; `abort` (or an exception inside a
    ``with`` block) deletes the temporary file.

    Args:
        recording: a dedicated stream whose sinks are already set.
        rrd_path: final path of the ``.rrd`` file, or None (viewer only).
        tmp_path: the file the stream's file sink writes to (required with ``rrd_path``).
        max_points_per_cloud: clouds above this are randomly subsampled (fixed seed).
        max_merged_points: cap for the residual heat map cloud.
        max_lines_per_pair: correspondences drawn per pair.
        max_pairs: pairs drawn in total; further pairs are skipped.
        seed: seed of the subsampling, so the same run gives the same recording.
    """

    def __init__(
        self,
        recording,
        *,
        rrd_path: Path | None = None,
        tmp_path: Path | None = None,
        warnings: Sequence[str] = (),
        max_points_per_cloud: int = 50_000,
        max_merged_points: int = 200_000,
        max_lines_per_pair: int = 200,
        max_pairs: int = 200,
        seed: int = 0,
    ) -> None:
        super().__init__(warnings)
        if (rrd_path is None) != (tmp_path is None):
            raise ValueError("rrd_path and tmp_path go together")
        self.rrd_path = None if rrd_path is None else Path(rrd_path)
        self._tmp_path = None if tmp_path is None else Path(tmp_path)
        self._rec = recording
        self.max_points_per_cloud = int(max_points_per_cloud)
        self.max_merged_points = int(max_merged_points)
        self.max_lines_per_pair = int(max_lines_per_pair)
        self.max_pairs = int(max_pairs)
        self._seed = seed
        self._color_index: dict[str, int] = {}
        self._axis_length: float | None = None
        self._pairs_logged = 0
        self._closed = False
        self._rec.send_blueprint(make_blueprint(), make_active=True, make_default=True)

    @property
    def enabled(self) -> bool:
        return not self._closed

    # -- logging ---------------------------------------------------------------------

    def log_config(self, config: Mapping | str) -> None:
        import rerun as rr

        if isinstance(config, str):
            text = config
        else:
            text = json.dumps(config, indent=2, default=_json_default)
        self._rec.log(
            "config",
            rr.TextDocument(f"```json\n{text}\n```", media_type="text/markdown"),
            static=True,
        )

    def log_raw_scans(self, names: Sequence[str], points_list: Sequence[np.ndarray]) -> None:
        import rerun as rr

        _check_same_length(names=names, points_list=points_list)
        for name, points in zip(names, points_list, strict=True):
            points = self._subsample(_as_points(points, name), self.max_points_per_cloud)
            self._update_axis_length(points)
            self._rec.log(["raw", name], rr.Points3D(points, colors=self._color(name)), static=True)

    def log_solver_iteration(
        self,
        step: int,
        objective: float | None = None,
        primal_residual: float | None = None,
        dual_residual: float | None = None,
        rho: float | None = None,
    ) -> None:
        import rerun as rr

        self._rec.set_time(SOLVER_TIMELINE, sequence=int(step))
        values = (objective, primal_residual, dual_residual, rho)
        for name, value in zip(SOLVER_SCALARS, values, strict=True):
            if value is not None:
                self._rec.log(f"solver/{name}", rr.Scalars(float(value)))
        # Everything else is static; keep the timeline from leaking into later calls.
        self._rec.disable_timeline(SOLVER_TIMELINE)

    def log_aligned(
        self,
        names: Sequence[str],
        points_list: Sequence[np.ndarray],
        T_world_scan: Sequence[np.ndarray],
    ) -> None:
        import rerun as rr

        _check_same_length(names=names, points_list=points_list, T_world_scan=T_world_scan)
        for name, points, pose in zip(names, points_list, T_world_scan, strict=True):
            points = self._subsample(_as_points(points, name), self.max_points_per_cloud)
            self._update_axis_length(points)
            self._log_pose(["world", "scans", name], pose, name)
            self._rec.log(
                ["world", "scans", name, "points"],
                rr.Points3D(points, colors=self._color(name)),
                static=True,
            )

    def log_pair_correspondences(
        self,
        name_a: str,
        name_b: str,
        points_a_world: np.ndarray,
        points_b_world: np.ndarray,
        weight: float | None = None,
    ) -> None:
        import rerun as rr

        if self._pairs_logged >= self.max_pairs:
            if self._pairs_logged == self.max_pairs:
                logger.info("recording: more than %d pairs, skipping the rest", self.max_pairs)
                self._pairs_logged += 1
            return
        a = _as_points(points_a_world, f"{name_a} (pair with {name_b})", keep_nonfinite=True)
        b = _as_points(points_b_world, f"{name_b} (pair with {name_a})", keep_nonfinite=True)
        if a.shape != b.shape:
            raise ValueError(f"pair {name_a}-{name_b}: {a.shape} and {b.shape} points differ")
        keep = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
        index = self._subsample_index(int(keep.sum()), self.max_lines_per_pair)
        segments = np.stack([a[keep][index], b[keep][index]], axis=1)
        # Green for a trusted pair, red for one the robust re-weighting switched off.
        w = 1.0 if weight is None else float(np.clip(weight, 0.0, 1.0))
        color = np.array([255 * (1.0 - w), 200 * w, 60], dtype=np.uint8)
        self._rec.log(
            ["world", "pairs", f"{name_a}--{name_b}"],
            rr.LineStrips3D(segments, colors=color),
            static=True,
        )
        self._pairs_logged += 1

    def log_residual_heatmap(
        self, points_world: np.ndarray, residuals: np.ndarray, clip_percentile: float = 95.0
    ) -> None:
        import rerun as rr

        points = _as_points(points_world, "residual heat map", keep_nonfinite=True)
        residuals = np.asarray(residuals, dtype=np.float64).reshape(-1)
        if len(residuals) != len(points):
            raise ValueError(f"{len(points)} points but {len(residuals)} residuals")
        keep = np.isfinite(points).all(axis=1)
        points, residuals = points[keep], residuals[keep]
        index = self._subsample_index(len(points), self.max_merged_points)
        points, residuals = points[index], residuals[index]
        colors, clip = residual_colors(residuals, clip_percentile)
        self._rec.log(
            ["residual_heatmap", "merged"],
            rr.Points3D(points, colors=colors),
            rr.AnyValues(residual=residuals.astype(np.float32)),
            static=True,
        )
        legend = (
            f"Residual heat map: viridis from 0 (purple) to {clip:.6g} (yellow), "
            f"the {clip_percentile:g}th percentile; larger residuals are clipped."
        )
        self._rec.log(["residual_heatmap", "legend"], rr.TextDocument(legend), static=True)

    def log_ground_truth(
        self,
        names: Sequence[str],
        T_world_scan_true: Sequence[np.ndarray],
        points_list: Sequence[np.ndarray] | None = None,
    ) -> None:
        import rerun as rr

        _check_same_length(names=names, T_world_scan_true=T_world_scan_true)
        if points_list is not None:
            _check_same_length(names=names, points_list=points_list)
        for i, (name, pose) in enumerate(zip(names, T_world_scan_true, strict=True)):
            self._log_pose(["world", "ground_truth", name], pose, name)
            if points_list is not None:
                points = self._subsample(
                    _as_points(points_list[i], name), self.max_points_per_cloud
                )
                self._rec.log(
                    ["world", "ground_truth", name, "points"],
                    rr.Points3D(points, colors=[160, 160, 160]),
                    static=True,
                )

    # -- lifetime --------------------------------------------------------------------

    def close(self) -> None:
        """Flush, finalize the file (footer) and rename it onto ``rrd_path``."""
        if self._closed:
            return
        self._closed = True
        try:
            try:
                self._rec.flush()
                self._rec.disconnect()  # drops the file sink, which writes the footer
            except RuntimeError as e:  # the file sink's writer died (disk full, ...)
                from mvreg.io.atomic import OutputWriteError

                if self._tmp_path is not None:
                    _check_not_cut_by_full_disk(self._tmp_path, self.rrd_path)
                raise OutputWriteError(self.rrd_path or "recording", _why(e)) from e
            if self._tmp_path is not None:
                _check_not_cut_by_full_disk(self._tmp_path, self.rrd_path)
                os.replace(self._tmp_path, self.rrd_path)
                logger.info("recording written to %s", self.rrd_path)
        except BaseException:
            self._discard_tmp()
            raise

    def abort(self) -> None:
        """Stop recording and delete the temporary file; ``rrd_path`` is left untouched."""
        if self._closed:
            return
        self._closed = True
        try:
            self._rec.disconnect()
        finally:
            self._discard_tmp()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"Recorder(rrd_path={self.rrd_path!s}, {state}, warnings={self.warnings!r})"

    # -- helpers ---------------------------------------------------------------------

    def _discard_tmp(self) -> None:
        if self._tmp_path is not None:
            self._tmp_path.unlink(missing_ok=True)

    def _color(self, name: str) -> np.ndarray:
        """The same color for a scan wherever it appears (raw, aligned)."""
        index = self._color_index.setdefault(name, len(self._color_index))
        return scan_colors(index + 1)[index]

    def _subsample_index(self, n: int, max_points: int) -> np.ndarray:
        if n <= max_points:
            return np.arange(n)
        rng = np.random.default_rng(self._seed)
        return np.sort(rng.choice(n, size=max_points, replace=False))

    def _subsample(self, points: np.ndarray, max_points: int) -> np.ndarray:
        return points[self._subsample_index(len(points), max_points)]

    def _update_axis_length(self, points: np.ndarray) -> None:
        # Units are whatever the scans use: size the pose axes from the first cloud seen.
        if self._axis_length is None and len(points) > 1:
            extent = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
            if extent > 0:
                self._axis_length = 0.1 * extent

    def _log_pose(self, entity_path: list[str], pose: np.ndarray, name: str) -> None:
        import rerun as rr

        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise ValueError(f"{name}: pose must be a finite (4, 4) matrix, got {pose.shape}")
        self._rec.log(
            entity_path,
            rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]),
            rr.TransformAxes3D(self._axis_length or 1.0),
            static=True,
        )


def make_blueprint():
    """Viewer layout: raw, aligned and residual 3D views over the solver plots."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial3DView(origin="raw", name="Raw scans"),
                rrb.Spatial3DView(origin="world", name="Aligned scans"),
                rrb.Spatial3DView(origin="residual_heatmap", name="Residual heat map"),
            ),
            rrb.Horizontal(
                rrb.TimeSeriesView(origin="solver", contents="$origin/objective", name="Objective"),
                rrb.TimeSeriesView(
                    origin="solver",
                    contents=["$origin/primal_residual", "$origin/dual_residual"],
                    name="Residuals",
                ),
                rrb.TimeSeriesView(origin="solver", contents="$origin/rho", name="rho"),
                rrb.TextDocumentView(origin="config", name="Configuration"),
            ),
            row_shares=[3, 1],
        ),
    )


def make_recorder(
    rrd_path: str | os.PathLike | None,
    spawn: bool = False,
    application_id: str = "mvreg",
    recording_id: str | None = None,
    *,
    viewer_port: int = DEFAULT_VIEWER_PORT,
    **options,
) -> NullRecorder:
    """Decide where the recording goes: ``rrd_path``, a spawned viewer, both, or nowhere.

    Returns a `Recorder` when there is at least one destination, else a `NullRecorder`.
    A viewer that cannot be opened (none installed, no display, failed start) is not an
    error: the reason is logged and listed in the returned object's ``warnings``.
    ``options`` go to `Recorder` (``max_points_per_cloud``, ``seed``, ...).
    """
    import rerun as rr

    warnings: list[str] = []
    if rrd_path is None and not spawn:
        return NullRecorder()
    recording = rr.RecordingStream(application_id, recording_id=recording_id)
    if not recording.is_enabled():
        return NullRecorder(_warn(warnings, "rerun logging is disabled (RERUN=off); no recording"))
    sinks = []
    if spawn:
        problem = _spawn_viewer(recording, viewer_port)
        if problem is None:
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{viewer_port}/proxy"))
        else:
            _warn(warnings, problem)
    tmp_path = None
    if rrd_path is not None:
        rrd_path = Path(rrd_path)
        tmp_path = _temp_path_beside(rrd_path)
        sinks.append(rr.FileSink(tmp_path))
    if not sinks:
        return NullRecorder(warnings)
    recording.set_sinks(*sinks)
    return Recorder(recording, rrd_path=rrd_path, tmp_path=tmp_path, warnings=warnings, **options)


def _why(e: Exception) -> str:
    """The reason of a failed recording: the file system's when it is full."""
    text = str(e).splitlines()[0] if str(e) else type(e).__name__
    return "No space left on device" if "No space" in str(e) else text


def _check_not_cut_by_full_disk(tmp_path: Path, rrd_path: Path) -> None:
    """OutputWriteError naming ``rrd_path`` when its file system is full: rerun's file sink
    only logs a failed write (the file is then cut short), it raises nothing."""
    from mvreg.io.atomic import OutputWriteError

    st = os.statvfs(tmp_path.parent)
    if st.f_bavail * st.f_frsize < 4096 and st.f_blocks > 0:
        raise OutputWriteError(rrd_path, "No space left on device")


def find_viewer_executable() -> str | None:
    """Path of an installed rerun viewer, or None.

    Looks on PATH, then beside the running interpreter (a venv not on PATH), then in the
    ``rerun_cli`` package that ships the binary with ``rerun-sdk``.
    """
    found = shutil.which("rerun") or shutil.which("rerun", path=str(Path(sys.executable).parent))
    if found:
        return found
    try:
        import rerun_cli
    except ImportError:
        return None
    binary = Path(rerun_cli.__file__).parent / "rerun"
    return str(binary) if binary.is_file() and os.access(binary, os.X_OK) else None


def _spawn_viewer(recording, port: int) -> str | None:
    """Start a viewer listening on ``port``; return None on success, else the reason."""
    import rerun as rr

    executable = find_viewer_executable()
    if executable is None:
        return "no rerun viewer is installed, not opening one (install rerun-sdk's viewer)"
    if sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        return "no display (DISPLAY / WAYLAND_DISPLAY unset), not opening the rerun viewer"
    try:
        rr.spawn(
            port=port,
            connect=False,
            hide_welcome_screen=True,
            executable_path=executable,
            recording=recording,
        )
    except Exception as error:  # the viewer is optional: any failure only loses the view
        return f"could not start the rerun viewer: {error}"
    return None


def _temp_path_beside(path: Path) -> Path:
    """A new hidden file beside ``path``; OutputWriteError naming ``path`` when the place
    cannot hold it (missing, read-only, not a folder)."""
    from mvreg.io.atomic import OutputWriteError

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".rrd", dir=path.parent)
    except OSError as e:
        raise OutputWriteError(path, e.strerror or str(e)) from e
    os.close(fd)
    return Path(tmp)


def _warn(warnings: list[str], message: str) -> list[str]:
    logger.warning("recording: %s", message)
    warnings.append(message)
    return warnings


def _as_points(points: np.ndarray, name: str, keep_nonfinite: bool = False) -> np.ndarray:
    """``(N, 3)`` float32 copy; rows with NaN/inf dropped unless ``keep_nonfinite``."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"{name}: expected (N, 3) points, got shape {points.shape}")
    points = np.asarray(points[:, :3], dtype=np.float32)
    if keep_nonfinite:
        return points
    return points[np.isfinite(points).all(axis=1)]


def _check_same_length(**sequences: Sequence) -> None:
    lengths = {key: len(value) for key, value in sequences.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"lengths differ: {lengths}")


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return str(value)
