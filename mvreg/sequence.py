"""register_sequence(): ordered range scans (a moving LiDAR) in, globally aligned poses out.

Reads as its stages:

load (natural order) -> timestamps and gaps -> KISS-ICP odometry -> preprocess (normals
towards the sensor) -> consecutive and skip pairs from the odometry, each verified by
ICP -> loop-closure candidates where the chained poses come back, each verified by ICP
-> pose tracks -> global solve (REG-ADMM) -> robust re-weighting -> refinement of the
pairs the solution disagrees with -> evaluation and drift report.

Conventions and choices (numbers quoted are from ``scripts/bench_sequence.py`` data):

* A scan is a set of points in its sensor frame (the sensor at the origin), as a LiDAR
  writes them; files are taken in natural order of their names.
* Timestamps: ``timestamps.txt`` in the folder, either one number per line (one per
  scan, in scan order) or ``name number`` lines (any order; lines for absent files are
  ignored); else the last number in each file name (``scan_012.ply`` -> 12,
  ``1317357625.557814.pcd`` -> 1317357625.557814); else the scan index. A one-per-line
  file whose length does not match the scans (a scan file was removed) is ignored with a
  warning in the report. Only ratios of time steps are used, so the unit does not
  matter. A time step above ``gap_factor`` times the median step is a *gap* (a missing
  scan, a pause); gaps are listed in the report and the scans on both sides are still
  paired, with a motion guess scaled to the longer step.
* Odometry: KISS-ICP (its Python API) over consecutive scans, deskewing off (scans carry
  no per-point times). Its settings are scaled to the data, never assumed in metres:
  ``max_range`` = the largest point range of the sequence, voxel =
  ``odometry_voxel_ranges`` * max_range (KISS-ICP's own default ratio 1/100), initial
  threshold 2 voxels and minimum motion 0.1 voxel (KISS-ICP's default ratios). Its
  constant-velocity prediction is rescaled by the ratio of time steps.
* Preprocessing: the voxel levels of ``register``, but every normal is turned towards the
  sensor and estimated from ``normal_neighbours`` nearest points: along a LiDAR ring the
  nearest points lie on a line, and the radius-based normals of ``register`` then tilt
  (pairwise ICP rotation error 0.11 deg median with them, 0.013 deg with these, on 22
  pairs of a 10,000-point sequence).
* Pairs: (k, k+1) by point-to-plane ICP (feature level, then fine level) from the
  odometry's relative pose, and again from a constant-velocity guess (the previous
  verified step) where that differs: KISS-ICP can lose track (sparse scans whose ground
  rings look alike from scan to scan, fast turns) while ICP from a good guess still
  converges. Then skip pairs (k, k+2 .. k+1+``skip_pairs``) from the odometry and from
  the chain of verified steps. Of several alignments of one pair the one bringing more
  of the scans into contact (fitness) is kept. Scores and the acceptance rule are those
  of ``register``, except the residual scale (:func:`calibrate_noise`). A pair still
  rejected is tried with feature RANSAC (``fallback_ransac``), which needs no guess.
* Loop closures: scan j is a candidate partner of an earlier scan i when, on the poses
  chained from the verified steps, they are at least ``loop_min_frames`` apart, the
  path between them is at least ``loop_min_path_radii`` radii, and they are within
  ``radius + loop_drift_fraction * path``, radius = ``loop_radius_ranges`` * the median
  point range (the scale at which range scans overlap). Each is verified by ICP from the
  chained guess (then feature RANSAC) and must also overlap by ``loop_min_overlap_ratio``.
* Global stage: :func:`pose_tracks` turn each accepted pair's alignment into point
  correspondences (a pose graph in REG form), then ``solve_tracks`` and ``robust_rounds``
  of :mod:`mvreg.refine`, and :func:`refine_pose_graph`. (``correspondences="nearest"``
  uses mutual nearest neighbours and multiview ICP as ``register`` does: less accurate
  on sparse scans, see :func:`pose_tracks`.)
* A scan that no accepted pair connects to the rest is listed in ``unregistered``, never
  given a pose made up from the odometry.
* Drift: the position of the last scan seen from the first, from KISS-ICP alone and
  after the global solve, against the ground truth when given, and, when a verified loop
  closure joins the end of the sequence to its start, against that measurement (a
  consistency check, not an independent error: the solve used that pair).
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ValidationError
from scipy.spatial import cKDTree

from mvreg.config import RegisterConfig, load_config
from mvreg.config.preprocess import PreprocessConfig
from mvreg.config.sequence import SequenceConfig
from mvreg.config.tracks import TracksConfig
from mvreg.errors import ConfigError, InputError
from mvreg.executor import single_threaded_blas
from mvreg.geometry import invert_transform, rotation_angle_deg, transform_points
from mvreg.io.loaders import Scan
from mvreg.joint_icp import joint_icp
from mvreg.metrics import pose_errors
from mvreg.pairwise import (
    PairResult,
    align_pair,
    fine_icp,
    make_aligner,
    pair_seed,
    rescore,
)
from mvreg.pairwise.preprocess import (
    PreprocessedScan,
    derive_voxel_size,
    outlier_mask,
    plane_noise,
)
from mvreg.pairwise.tracks import (
    Tracks,
    build_tracks,
    tracks_from_correspondences,
)
from mvreg.pipeline import Registration, load_source
from mvreg.refine import (
    GlobalSolution,
    pair_residuals,
    refine_rounds,
    robust_rounds,
    robust_weights,
    solve_tracks,
)
from mvreg.viz import NullRecorder

TIMESTAMPS_FILE = "timestamps.txt"
# Refinement re-aligns a pair whose points lie this many voxels apart under the global poses.
REFINE_DISAGREEMENT_VOXELS = 0.1


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


@dataclass(repr=False)
class SequenceRegistration(Registration):
    """The result of :func:`register_sequence`: a :class:`~mvreg.pipeline.Registration`
    plus the sequence's timestamps, KISS-ICP's own poses and the sequence report.

    T_odom_scan: {scan name: (4, 4)} KISS-ICP poses (odometry frame = first scan).
    timestamps: {scan name: time} as read (unit of the source).
    sequence: the ``"sequence"`` section of report.json (timestamps source, gaps,
        odometry, pairs by kind, loop closures, drift, warnings).
    """

    timestamps: dict[str, float] = field(default_factory=dict)
    T_odom_scan: dict[str, np.ndarray] = field(default_factory=dict)
    sequence: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        drift = self.sequence.get("drift", {})
        odo = drift.get("odometry_end_to_start_vs_truth")
        fin = drift.get("global_end_to_start_vs_truth")
        extra = "" if odo is None or fin is None else f", drift {odo:.3g} -> {fin:.3g}"
        return (
            f"SequenceRegistration(scans={len(self.scan_names)}, "
            f"registered={len(self.T_world_scan)}, unregistered={self.unregistered}, "
            f"loop_closures={self.sequence.get('loop_closures', {}).get('accepted')}{extra}, "
            f"time={self.timings.get('total', float('nan')):.2f}s)"
        )

    def report(self) -> dict:
        out = super().report()
        out["sequence"] = self.sequence
        return out


class _NoProgress:
    def stage(self, name: str, total: int | None = None) -> None: ...
    def advance(self, n: int = 1) -> None: ...
    def done(self) -> None: ...


def register_sequence(
    source: str | Path | Sequence[np.ndarray],
    config: RegisterConfig | None = None,
    *,
    sequence: SequenceConfig | None = None,
    names: Sequence[str] | None = None,
    timestamps: Sequence[float] | None = None,
    recorder=None,
    progress=None,
    truth: dict[str, np.ndarray] | None = None,
    **overrides,
) -> SequenceRegistration:
    """Register an ordered sequence of range scans (see the module docstring).

    Args:
        source: folder of scan files (natural order), or (N_k, 3) point arrays in their
            sensor frames, in time order.
        config: a RegisterConfig; else defaults with ``overrides`` (dotted keys, as for
            :func:`mvreg.pipeline.register`). Keys starting with ``sequence.`` set the
            :class:`SequenceConfig` (e.g. ``**{"sequence.skip_pairs": 2}``).
        sequence: a SequenceConfig (default: defaults and the ``sequence.`` overrides).
        names: names of the arrays when ``source`` is a list.
        timestamps: one time per scan (overrides ``timestamps.txt`` and file names).
        recorder: a mvreg.viz Recorder (default: none).
        progress: an object with stage(name, total) / advance(n) / done().
        truth: {name: (4, 4) T_world_scan} to evaluate against; by default read from
            ``ground_truth.json`` in the folder. Used only to evaluate, never to solve.
    Raises:
        InputError: fewer than 2 scans, bad timestamps, bad arrays; ScanFileError for an
            unreadable scan; ConfigError for bad settings.
    """
    cfg, seq = _resolve_config(config, sequence, overrides)
    rec = recorder if recorder is not None else NullRecorder()
    prog = progress if progress is not None else _NoProgress()
    timings: dict = {}
    t_start = time.perf_counter()
    clock = [t_start]

    def timed(name: str) -> None:
        now = time.perf_counter()
        timings[name] = now - clock[0]
        clock[0] = now

    warnings: list[str] = []
    scans, source_str, truth, folder = _load(source, names, cfg, truth, prog)
    times, time_source = _timestamps(scans, folder, timestamps, warnings)
    gaps = find_gaps(times, seq.gap_factor)
    timed("load")
    rec.log_config({**cfg.model_dump(mode="json"), "sequence": seq.model_dump(mode="json")})
    rec.log_raw_scans([s.name for s in scans], [s.points for s in scans])

    prog.stage("odometry", len(scans))
    odom = kiss_icp_odometry([s.points for s in scans], times, seq, advance=prog.advance)
    timed("odometry")

    voxel = derive_voxel_size(scans, cfg.preprocess)
    prog.stage("preprocess", len(scans))
    pre = []
    for s in scans:
        pre.append(preprocess_range_scan(s, voxel, cfg.preprocess, seq))
        prog.advance()
    timed("preprocess")

    results, noise = sequential_results(pre, odom, times, cfg, seq, prog)
    if noise is None:
        warnings.append("no consecutive scans are in contact: residual scale not calibrated")
    timed("sequential_pairs")
    loops = loop_closures(
        pre, scans, chain_poses(odom.T_odom_scan, results), results, cfg, seq, prog
    )
    results += loops.results
    timed("loop_closures")

    step = [0]

    def on_iteration(r):
        step[0] += 1
        rec.log_solver_iteration(step[0], r.objective, r.primal_residual, r.dual_residual, r.rho)

    glob = _global_stage(pre, results, cfg, seq, prog, timed, on_iteration)
    prog.done()

    names_all = [s.name for s in scans]
    sol = glob.solution
    T = {} if sol is None else {names_all[i]: sol.T_world_scan[i] for i in sorted(sol.T_world_scan)}
    reg = SequenceRegistration(
        scan_names=names_all,
        T_world_scan=T,
        unregistered=[n for n in names_all if n not in T],
        solve=None if sol is None else sol.result,
        pairs=_pair_table(glob.results, glob.tracks, glob.weights),
        config=cfg,
        voxel_size=voxel,
        timings=timings,
        robust_log=glob.robust_log,
        refine_log=glob.refine_log,
        joint_icp=glob.joint_icp,
        scans=scans,
        source=source_str,
        timestamps=dict(zip(names_all, times.tolist(), strict=True)),
        T_odom_scan=dict(zip(names_all, odom.T_odom_scan, strict=True)),
    )
    _evaluate(reg, pre, glob.results, truth)
    reg.sequence = _sequence_report(
        reg, seq, odom, time_source, gaps, glob.results, loops, noise, truth, warnings
    )
    timed("evaluate")
    timings["total"] = time.perf_counter() - t_start
    if T:
        idx = [names_all.index(n) for n in T]
        rec.log_aligned(list(T), [scans[i].points for i in idx], list(T.values()))
    return reg


@dataclass
class _GlobalStage:
    solution: GlobalSolution | None
    tracks: Tracks
    weights: np.ndarray
    results: list[PairResult]
    robust_log: list[dict]
    refine_log: list[dict]
    joint_icp: dict | None = None


def _global_stage(pre, results, cfg: RegisterConfig, seq: SequenceConfig, prog, timed, callback):
    """Tracks -> global solve -> robust re-weighting -> refinement."""
    prog.stage("global solve")
    tcfg = _tracks_config(cfg, seq)
    per_pair = tcfg.max_correspondences_per_pair or seq.correspondences_per_pair or 400
    if seq.correspondences == "pose":
        tracks = pose_tracks(pre, results, per_pair)
    else:
        tracks = build_tracks(pre, results, tcfg)
    out = _GlobalStage(None, tracks, np.zeros(len(tracks.pairs)), list(results), [], [])
    if tracks.problem is None:
        return out
    sol = solve_tracks(tracks, cfg, callback=callback)
    timed("tracks_and_solve")
    prog.stage("robust re-weighting")
    sol, out.weights, out.robust_log = robust_rounds(
        tracks, sol, pre[0].voxel_size, cfg, callback=callback
    )
    timed("robust")
    prog.stage("refinement", cfg.refine.rounds)
    if seq.correspondences == "pose":
        sol, out.tracks, out.weights, out.results, out.refine_log = refine_pose_graph(
            pre, sol, tracks, out.results, out.weights, cfg, per_pair, callback=callback
        )
    else:
        graph = [
            (int(i), int(j)) for (i, j), w in zip(tracks.pairs, out.weights, strict=True) if w > 0
        ]
        sol, out.refine_log = refine_rounds(
            pre, sol, cfg, callback=callback, pairs=graph, tracks_cfg=tcfg
        )
    if cfg.refine.rounds:  # over the pairs the global stage kept
        pairs_w = zip(out.tracks.pairs, out.weights, strict=True)
        kept = [(int(i), int(j)) for (i, j), w in pairs_w if w > 0]
        sol, out.joint_icp = joint_icp(pre, sol, cfg, pairs=kept, tracks_cfg=tcfg)
    timed("refine")
    out.solution = sol
    return out


# ---------------------------------------------------------------------------- config


def _resolve_config(
    config: RegisterConfig | None, sequence: SequenceConfig | None, overrides: dict
) -> tuple[RegisterConfig, SequenceConfig]:
    seq_over = {k[len("sequence.") :]: v for k, v in overrides.items() if k.startswith("sequence.")}
    rest = {k: v for k, v in overrides.items() if not k.startswith("sequence.")}
    if config is not None and rest:
        raise ConfigError(f"give either a config or overrides, not both ({', '.join(rest)})")
    cfg = config if config is not None else load_config(**rest)
    if sequence is None and not seq_over and isinstance(getattr(cfg, "sequence", None), BaseModel):
        sequence = cfg.sequence  # a RegisterConfig that carries the sequence settings
    if sequence is None:
        try:
            sequence = SequenceConfig(**{k: v for k, v in seq_over.items() if v is not None})
        except ValidationError as e:
            err = e.errors()[0]
            where = ".".join(str(x) for x in err["loc"])
            raise ConfigError(f"sequence.{where}: {err['msg']}") from None
    elif seq_over:
        raise ConfigError("give either a SequenceConfig or sequence.* overrides, not both")
    return cfg, sequence


def _tracks_config(cfg: RegisterConfig, seq: SequenceConfig) -> TracksConfig:
    update = {}
    if cfg.tracks.max_correspondences_per_pair is None:
        update["max_correspondences_per_pair"] = seq.correspondences_per_pair
    if "min_normal_cos" not in cfg.tracks.model_fields_set:
        update["min_normal_cos"] = seq.min_normal_cos
    return cfg.tracks.model_copy(update=update)


# ---------------------------------------------------------------------------- load


def _load(source, names, cfg: RegisterConfig, truth, prog):
    """Scans in order, the source as text, the truth (read from the folder if not
    given) and the folder (None for arrays)."""
    scans, src, truth = load_source(source, names, cfg, truth, prog, what="a sequence")
    folder = Path(source) if isinstance(source, (str, Path)) else None
    return scans, src, truth, folder


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


def _timestamps(scans, folder, given, warnings: list[str]) -> tuple[np.ndarray, str]:
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


# ---------------------------------------------------------------------------- odometry


def _scale_motion(T: np.ndarray, s: float) -> np.ndarray:
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
            odometry.last_delta = _scale_motion(odometry.last_delta, dt[k - 1] / dt[k - 2])
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


# ---------------------------------------------------------------------------- preprocess


def preprocess_range_scan(
    scan: Scan,
    voxel_size: float,
    cfg: PreprocessConfig | None = None,
    seq: SequenceConfig | None = None,
) -> PreprocessedScan:
    """Downsample a range scan and orient every normal towards its sensor (the origin).

    Like :func:`mvreg.pairwise.preprocess.preprocess` (same levels, outlier removal and
    noise estimate) except for the normals: a range scan sees every surface from the
    sensor, so each normal is turned to face it, which is exact where the tangent-plane
    propagation of ``preprocess`` fails (a LiDAR scan is many disconnected pieces). A
    surround scan is no single view, so ``view_direction`` is None (no free-space test).
    FPFH features are computed on demand by :func:`ensure_features` (only the feature
    RANSAC fallback needs them); until then ``features`` is an empty (0, 33) array.
    """
    import open3d as o3d

    cfg = cfg or PreprocessConfig()
    seq = seq or SequenceConfig()
    v = float(voxel_size)
    if not v > 0:
        raise ConfigError(f"voxel_size must be > 0, got {voxel_size}")
    keep = (
        outlier_mask(scan.points, v, cfg.outlier_min_cell_share)
        if cfg.outlier_min_cell_share > 0
        else np.ones(scan.num_points, bool)
    )
    raw = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(np.ascontiguousarray(scan.points[keep], dtype=np.float64))
    )
    origin = np.zeros(3) if scan.sensor_origin is None else np.asarray(scan.sensor_origin, float)

    def level(voxel: float):
        down = raw.voxel_down_sample(voxel)
        down.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=seq.normal_radius_voxels * voxel, max_nn=seq.normal_neighbours
            )
        )
        down.orient_normals_towards_camera_location(origin)
        return down, np.asarray(down.points).copy(), np.asarray(down.normals).copy()

    with single_threaded_blas():
        coarse, pts, nrm = level(v)
        if len(pts) < 10:
            raise ConfigError(
                f"{scan.name}: only {len(pts)} points at voxel size {v:.4g}; the voxel is too "
                "large for this scan"
            )
        fine_v = cfg.fine_voxel_ratio * v
        _, fine_pts, fine_nrm = level(fine_v)
        out = PreprocessedScan(
            name=scan.name,
            voxel_size=v,
            points=pts,
            normals=nrm,
            features=np.zeros((0, 33)),
            fine_voxel_size=fine_v,
            fine_points=fine_pts,
            fine_normals=fine_nrm,
            noise=plane_noise(fine_pts, fine_nrm),
            orientation="sensor origin",
            num_raw_points=scan.num_points,
            num_outliers_removed=int(np.count_nonzero(~keep)),
        )
    out._cache["o3d_feature"] = coarse
    return out


def ensure_features(pre: PreprocessedScan, cfg: PreprocessConfig | None = None) -> None:
    """Compute the FPFH features of ``pre`` (N, 33) if they are not there yet (in place)."""
    import open3d as o3d

    if len(pre.features) == len(pre.points):
        return
    cfg = cfg or PreprocessConfig()
    with single_threaded_blas():
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            pre.o3d_cloud("feature"),
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=cfg.fpfh_radius_voxels * pre.voxel_size, max_nn=cfg.fpfh_max_neighbours
            ),
        )
    pre.features = np.asarray(fpfh.data).T.copy()
    pre._cache["o3d_fpfh"] = fpfh
    pre._cache.pop("reduced_features", None)


# ---------------------------------------------------------------------------- pairs


def sequential_pairs(num_scans: int, skip_pairs: int = 1) -> list[tuple[int, int]]:
    """(k, k+1), ..., (k, k+1+skip_pairs) for every k, in order of k."""
    return [
        (k, k + s) for k in range(num_scans) for s in range(1, skip_pairs + 2) if k + s < num_scans
    ]


def calibrate_noise(pre: Sequence[PreprocessedScan], results: Sequence[PairResult]) -> float | None:
    """Set every scan's ``noise`` to the residual that correct consecutive alignments leave.

    The within-scan estimate of :func:`~mvreg.pairwise.preprocess.preprocess` means
    nothing for a LiDAR scan: the nearest neighbours of a point lie along its ring, on
    a line, and the fitted tangent plane contains that line, so the estimate is near 0;
    and what a correct alignment of two such scans leaves is set by how differently
    their rings sample the scene, not by the range noise. So the reference is measured
    on the (k, k+1) pairs after ICP from the odometry: the lower quartile of their median
    residuals (robust while up to three quarters of them are wrong). Returns it, or None
    (``noise`` left as it was) when no consecutive pair has any point in contact.
    """
    med = [
        r.stats["median_residual"]
        for r in results
        if r.j == r.i + 1 and np.isfinite(r.stats.get("median_residual", np.inf))
    ]
    if not med:
        return None
    reference = max(float(np.percentile(med, 25)), 1e-12 * pre[0].voxel_size)
    for p in pre:
        p.noise = reference
    return reference


def _parallel(fn, items, workers: int, advance=None) -> list:
    out = []
    with single_threaded_blas():
        if workers == 1 or len(items) <= 1:
            for it in items:
                out.append(fn(it))
                if advance is not None:
                    advance()
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                for res in pool.map(fn, items):
                    out.append(res)
                    if advance is not None:
                        advance()
    return out


def _guess_distance(pre_j: PreprocessedScan, T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Median displacement of scan j's feature-level points between two guesses."""
    return float(
        np.median(
            np.linalg.norm(
                transform_points(T_a, pre_j.points) - transform_points(T_b, pre_j.points), axis=1
            )
        )
    )


def _better(a: PairResult, b: PairResult) -> PairResult:
    """Of two alignments of the same pair: the accepted one, else the larger fitness
    (the share of scan j brought into contact with scan i)."""
    return a if (a.accepted, a.fitness) >= (b.accepted, b.fitness) else b


def align_with_guesses(
    pre: Sequence[PreprocessedScan],
    pairs: Sequence[tuple[int, int]],
    guesses: Sequence[Sequence[tuple[str, np.ndarray]]],
    cfg: RegisterConfig,
    *,
    kind: str,
    advance: Callable[[], None] | None = None,
) -> list[PairResult]:
    """ICP of each pair (i, j) from each of its guesses ``(label, T_i_j)`` (skipping a
    guess within half a voxel of one already tried), keeping the better result
    (:func:`_better`). Runs on ``cfg.workers`` threads; results in the order
    of ``pairs`` with ``stats["kind"] = kind`` and ``stats["init"]`` = the guess's label.
    """
    icp_guess = make_aligner("icp-guess", cfg.align, cfg.search)
    icp_guess.prepare(pre)  # shared trees, built before the threads start

    def run(n: int) -> PairResult:
        i, j = pairs[n]
        best, tried = None, []
        for label, guess in guesses[n]:
            if any(_guess_distance(pre[j], guess, t) < 0.5 * pre[j].voxel_size for t in tried):
                continue
            tried.append(guess)
            res = icp_guess.align(pre[i], pre[j], guess, i=i, j=j)
            res.stats |= {"kind": kind, "init": label}
            best = res if best is None else _better(best, res)
        best.stats["guesses_tried"] = len(tried)
        return best

    return _parallel(run, list(range(len(pairs))), cfg.workers, advance)


def _relative(T_scan: np.ndarray, i: int, j: int) -> np.ndarray:
    return invert_transform(T_scan[i]) @ T_scan[j]


def sequential_results(
    pre: Sequence[PreprocessedScan],
    odom: Odometry,
    times: np.ndarray,
    cfg: RegisterConfig,
    seq: SequenceConfig,
    progress=None,
) -> tuple[list[PairResult], float | None]:
    """Consecutive pairs, then the skip pairs (see the module docstring).

    1. (k, k+1) by ICP from the odometry; the residual scale is calibrated on them
       (:func:`calibrate_noise`) and they are re-scored.
    2. (k, k+1) again from a constant-velocity guess (the verified step (k-1, k), scaled
       by the ratio of time steps) where it differs from the odometry's: when the
       odometry lost track (it predicts from its own, possibly wrong, velocity), this
       guess still lies in ICP's basin.
    3. Skip pairs (k, k+2 ..) from the odometry and from the chain of verified steps.
    4. Feature RANSAC for every pair still rejected (``fallback_ransac``).

    Returns the results (consecutive pairs first) and the calibrated residual scale.
    """
    prog = progress if progress is not None else _NoProgress()
    m = len(pre)
    T_odo = odom.T_odom_scan
    steps = [(k, k + 1) for k in range(m - 1)]
    prog.stage("consecutive pairs", len(steps))
    results = align_with_guesses(
        pre, steps, [[("odometry", _relative(T_odo, i, j))] for i, j in steps], cfg,
        kind="sequential", advance=prog.advance,
    )  # fmt: skip
    noise = calibrate_noise(pre, results)
    for r in results:
        rescore(r, pre[r.i], pre[r.j], cfg.align)
    dt = np.diff(times)
    redo, guesses = [], []
    for k in range(1, m - 1):
        prev = results[k - 1]
        if prev.accepted:
            cv = _scale_motion(prev.T_i_j, dt[k] / dt[k - 1])
            if (
                _guess_distance(pre[k + 1], cv, _relative(T_odo, k, k + 1))
                >= 0.5 * pre[k].voxel_size
            ):
                redo.append(k)
                guesses.append([("constant velocity", cv)])
    prog.stage("consecutive pairs: constant velocity", len(redo))
    again = align_with_guesses(
        pre, [steps[k] for k in redo], guesses, cfg, kind="sequential", advance=prog.advance
    )
    for k, res in zip(redo, again, strict=True):
        results[k] = _better(results[k], res)
    T_chain = chain_poses(T_odo, results)
    skips = [(i, j) for i, j in sequential_pairs(m, seq.skip_pairs) if j > i + 1]
    prog.stage("skip pairs", len(skips))
    skip_guesses = [
        [("odometry", _relative(T_odo, i, j)), ("chain", _relative(T_chain, i, j))]
        for i, j in skips
    ]
    results += align_with_guesses(
        pre, skips, skip_guesses, cfg, kind="sequential", advance=prog.advance
    )
    prog.stage("sequential pairs: feature RANSAC", sum(not r.accepted for r in results))
    return ransac_fallback(pre, results, cfg, seq, advance=prog.advance), noise


def ransac_fallback(
    pre: Sequence[PreprocessedScan],
    results: list[PairResult],
    cfg: RegisterConfig,
    seq: SequenceConfig,
    advance: Callable[[], None] | None = None,
) -> list[PairResult]:
    """Retry every rejected pair with feature RANSAC + ICP (:func:`~mvreg.pairwise.align_pair`),
    which needs no initial guess; a retry replaces the pair when it is accepted (for
    loop pairs, also with ``seq.loop_min_overlap_ratio``). Returns the new list."""
    todo = [k for k, r in enumerate(results) if not r.accepted]
    if not todo or not seq.fallback_ransac:
        return results
    for k in todo:
        ensure_features(pre[results[k].i], cfg.preprocess)
        ensure_features(pre[results[k].j], cfg.preprocess)

    def run(k: int) -> PairResult:
        old = results[k]
        alt = align_pair(
            pre[old.i], pre[old.j], cfg.align, pair_seed(cfg.seed, old.i, old.j), i=old.i, j=old.j
        )
        alt.stats |= {"init": "feature RANSAC", "kind": old.stats.get("kind", "")}
        alt.stats["odometry_attempt"] = old.reason
        _loop_gate(alt, seq)
        return alt if alt.accepted else old

    out = list(results)
    for k, res in zip(todo, _parallel(run, todo, cfg.workers, advance), strict=True):
        out[k] = res
    return out


@dataclass
class LoopClosures:
    """Loop-closure candidates and their verification.

    radius: the search radius at zero path (data units); candidates: (i, j) pairs tried;
    results: one PairResult per candidate (``stats["kind"] == "loop"``).
    """

    radius: float
    candidates: list[tuple[int, int]]
    results: list[PairResult]


def loop_closures(
    pre: Sequence[PreprocessedScan],
    scans: Sequence[Scan],
    T_chain: np.ndarray,
    done: Sequence[PairResult],
    cfg: RegisterConfig,
    seq: SequenceConfig,
    progress=None,
) -> LoopClosures:
    """Candidates from the chained poses (:func:`loop_candidates`, pairs in ``done``
    left out), each verified by ICP from the chained guess, then feature RANSAC; a loop
    pair must also overlap by ``seq.loop_min_overlap_ratio``.

    Args:
        T_chain: (M, 4, 4) poses chained from the verified consecutive pairs.
    """
    prog = progress if progress is not None else _NoProgress()
    ranges = [float(np.median(np.linalg.norm(s.points, axis=1))) for s in scans]
    radius = seq.loop_radius_ranges * float(np.median(ranges))
    tried = {(r.i, r.j) for r in done}
    pairs = [p for p in loop_candidates(T_chain, radius, seq) if p not in tried]
    prog.stage("loop closures", len(pairs))
    results = align_with_guesses(
        pre, pairs, [[("chain", _relative(T_chain, i, j))] for i, j in pairs], cfg,
        kind="loop", advance=prog.advance,
    )  # fmt: skip
    for r in results:
        _loop_gate(r, seq)
    prog.stage("loop closures: feature RANSAC", sum(not r.accepted for r in results))
    results = ransac_fallback(pre, results, cfg, seq, advance=prog.advance)
    return LoopClosures(radius, pairs, results)


def _loop_gate(res: PairResult, seq: SequenceConfig) -> None:
    if (
        res.stats.get("kind") == "loop"
        and res.accepted
        and res.overlap_ratio < seq.loop_min_overlap_ratio
    ):
        res.accepted = False
        res.reason = (
            f"loop closure overlap {res.overlap_ratio:.2f} below {seq.loop_min_overlap_ratio:.2f}"
        )


def chain_poses(T_odom_scan: np.ndarray, results: Sequence[PairResult]) -> np.ndarray:
    """(M, 4, 4) poses chained along the sequence, for finding loop-closure candidates.

    Scan k is placed from the nearest earlier scan i that an accepted sequential pair
    (i, k) links it to (i = k-1 when that pair was accepted; a skip pair bridges a scan
    that failed), else by the odometry's step from scan k-1.
    """
    into: dict[int, PairResult] = {}
    for r in results:
        if r.accepted and r.stats.get("kind") == "sequential" and r.i < r.j:
            if r.j not in into or r.i > into[r.j].i:
                into[r.j] = r
    out = np.empty_like(T_odom_scan)
    out[0] = np.eye(4)
    for k in range(1, len(T_odom_scan)):
        r = into.get(k)
        if r is not None:
            out[k] = out[r.i] @ r.T_i_j
        else:
            out[k] = out[k - 1] @ _relative(T_odom_scan, k - 1, k)
    return out


def loop_candidates(
    T_odom_scan: np.ndarray, radius: float, seq: SequenceConfig | None = None
) -> list[tuple[int, int]]:
    """Pairs (i, j), i < j, whose odometry positions came back close (module docstring).

    Args:
        T_odom_scan: (M, 4, 4) poses in one frame.
        radius: search radius at zero path (data units).
    Returns:
        at most ``loop_max_per_scan`` pairs per later scan j (its nearest), sorted.
    """
    seq = seq or SequenceConfig()
    pos = T_odom_scan[:, :3, 3]
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    out = []
    for j in range(len(pos)):
        i = np.arange(0, j - seq.loop_min_frames + 1)
        if len(i) == 0 or seq.loop_max_per_scan == 0:
            continue
        travelled = path[j] - path[i]
        dist = np.linalg.norm(pos[i] - pos[j], axis=1)
        ok = (travelled >= seq.loop_min_path_radii * radius) & (
            dist <= radius + seq.loop_drift_fraction * travelled
        )
        best = i[ok][np.argsort(dist[ok], kind="stable")[: seq.loop_max_per_scan]]
        out.extend((int(a), j) for a in best)
    return sorted(out)


# ---------------------------------------------------------------------------- refinement


def pose_tracks(
    pre: Sequence[PreprocessedScan],
    results: Sequence[PairResult],
    per_pair: int = 400,
) -> Tracks:
    """Tracks that carry each accepted pair's relative pose, not nearest neighbours.

    For an accepted pair (i, j), up to ``per_pair`` of scan j's fine points that land
    within one voxel of scan i's fine points under ``T_i_j`` (the overlap), evenly
    spread, each become a node observed by scan j at its own coordinates ``p`` and by
    scan i at ``T_i_j p``. Every node belongs to one pair, so the patch problem is a pose
    graph whose edges weigh each pair by where the two scans overlap; its solution
    honours every pair's ICP (point-to-plane) alignment as far as the loops allow.

    Why not mutual nearest neighbours (:func:`~mvreg.pairwise.build_tracks`): on sparse
    range scans two scans never sample the same physical points -- their rings cut the
    ground and walls along different curves, ~0.1 voxel apart and biased in a direction
    set by the motion -- so point-to-point links pull scans by the sampling pattern
    (measured on a 100-scan loop of 10,000-point scans: 0.56 deg median rotation error
    with nearest neighbours and ``register``'s multiview ICP, 0.045 deg with these).
    """
    m = len(pre)
    chunks: list[list[np.ndarray]] = [[] for _ in range(m)]
    sizes = np.zeros(m, np.int64)
    pairs, corr = [], []
    for r in results:
        if not r.accepted:
            continue
        moved = transform_points(r.T_i_j, pre[r.j].fine_points)
        d, _ = pre[r.i].fine_tree().query(moved, distance_upper_bound=pre[r.i].voxel_size)
        sel = np.flatnonzero(np.isfinite(d))
        if len(sel) < 3:
            continue
        if len(sel) > per_pair:
            sel = sel[np.linspace(0, len(sel) - 1, per_pair).round().astype(np.int64)]
        k = len(sel)
        chunks[r.i].append(moved[sel])
        chunks[r.j].append(pre[r.j].fine_points[sel])
        corr.append((sizes[r.i] + np.arange(k), sizes[r.j] + np.arange(k)))
        sizes[r.i] += k
        sizes[r.j] += k
        pairs.append((r.i, r.j))
    points = [np.vstack(c) if c else np.zeros((0, 3)) for c in chunks]
    return tracks_from_correspondences(
        points,
        [p.name for p in pre],
        np.array(pairs, dtype=np.int64).reshape(-1, 2),
        corr,
        distances=[np.zeros(len(c[0])) for c in corr],
    )


def refine_pose_graph(
    pre: Sequence[PreprocessedScan],
    sol: GlobalSolution,
    tracks: Tracks,
    results: Sequence[PairResult],
    weights: np.ndarray,
    cfg: RegisterConfig,
    per_pair: int,
    callback: Callable | None = None,
) -> tuple[GlobalSolution, Tracks, np.ndarray, list[PairResult], list[dict]]:
    """Refinement rounds for :func:`pose_tracks`: re-align the pairs the solution disagrees with.

    A pair whose linked points lie more than ``REFINE_DISAGREEMENT_VOXELS`` (0.1) voxels
    apart (median) under the global poses -- typically a loop closure whose ICP started
    from a drifted odometry guess and stopped in a nearby minimum -- is aligned again by
    fine point-to-plane ICP started from the global poses (``cfg.align`` distances);
    if still accepted it replaces the pair, and the problem is re-solved warm-started with
    weights from the residuals (``cfg.robust``). At most ``cfg.refine.rounds`` rounds,
    each pair re-aligned at most once; stops when no new pair disagrees. Pairs that
    agree are not re-aligned: ICP restarted from a nearby pose only moves within its
    stopping tolerance (measured: re-aligning every pair in every round, with the
    shrinking distances of ``register``'s refinement, made a 100-scan loop worse, 0.045
    -> 0.064 deg median rotation error).
    ``cfg.refine.distance_voxels`` is not used. Returns the solution, its tracks, their
    (P,) pair weights, the pair results (re-aligned ones replaced) and a log per round.
    """
    log: list[dict] = []
    results = list(results)
    voxel = pre[0].voxel_size if pre else 1.0
    index = {(r.i, r.j): k for k, r in enumerate(results)}
    realigned: set[int] = set()
    for k in range(cfg.refine.rounds):
        poses = sol.T_world_scan
        residual = pair_residuals(tracks, poses)
        todo = [
            index[(int(i), int(j))]
            for (i, j), res, w in zip(tracks.pairs, residual, weights, strict=True)
            if w > 0 and np.isfinite(res) and res > REFINE_DISAGREEMENT_VOXELS * voxel
        ]
        todo = [n for n in todo if n not in realigned]  # once each: ICP would not move it
        if not todo:
            break
        realigned.update(todo)

        def run(n: int, poses=poses) -> PairResult:
            r = results[n]
            guess = invert_transform(poses[r.i]) @ poses[r.j]
            with single_threaded_blas():
                T = fine_icp(
                    pre[r.i], pre[r.j], guess, cfg.align.icp_fine_distance_voxels, cfg.align, voxel
                )
            new = dataclasses.replace(r, T_i_j=T, stats=dict(r.stats))
            new.stats["refined_from"] = "global poses"
            return rescore(new, pre[r.i], pre[r.j], cfg.align)

        changed = 0
        for n, new in zip(todo, _parallel(run, todo, cfg.workers), strict=True):
            if new.accepted:
                results[n] = new
                changed += 1
        new_tracks = pose_tracks(pre, results, per_pair)
        if new_tracks.problem is None:
            break
        tracks = new_tracks
        weights = robust_weights(pair_residuals(tracks, poses), voxel, cfg.robust)
        prev = sol
        sol = solve_tracks(tracks.reweighted(weights), cfg, init=poses, callback=callback)
        log.append(
            {
                "round": k + 1,
                "pairs_disagreeing": len(todo),
                "pairs_realigned": changed,
                "pairs_zero_weight": int(np.sum(weights == 0)),
                "max_translation_change": max(
                    float(np.linalg.norm(sol.T_world_scan[s][:3, 3] - prev.T_world_scan[s][:3, 3]))
                    for s in sol.T_world_scan
                    if s in prev.T_world_scan
                ),
                "certified": sol.result.certified,
            }
        )
    return sol, tracks, weights, results, log


# ---------------------------------------------------------------------------- report


def _pair_table(results: list[PairResult], tracks, weights) -> list[dict]:
    w_of = {(int(i), int(j)): float(w) for (i, j), w in zip(tracks.pairs, weights, strict=True)}
    rows = []
    for r in results:
        rows.append(
            {
                "scans": list(r.names),
                "kind": r.stats.get("kind", ""),
                "init": r.stats.get("init", ""),
                "accepted": bool(r.accepted),
                "reason": r.reason,
                "overlap_ratio": r.overlap_ratio,
                "inlier_rmse": r.inlier_rmse,
                "num_correspondences": int(r.num_correspondences),
                "fitness": r.fitness,
                "residual_ratio": r.residual_ratio,
                "final_weight": w_of.get((r.i, r.j), 0.0) if r.accepted else 0.0,
                "seconds": r.seconds,
            }
        )
    return rows


def _evaluate(reg: SequenceRegistration, pre, results, truth) -> None:
    """Overlap residual over the pair graph; errors against ground truth when given.

    The overlap residual of ``register`` compares every scan with every other one; for a
    long sequence each scan is compared with its partners in the accepted pairs only.
    """
    if not reg.T_world_scan:
        return
    idx = {s.name: i for i, s in enumerate(reg.scans)}
    spacing = float(np.median([p.noise for p in pre]))
    thresh = max(2.0 * pre[0].fine_voxel_size, 10 * spacing)
    reg.overlap = _graph_overlap(reg, idx, results, thresh)
    if truth:
        common = [n for n in reg.T_world_scan if n in truth]
        if len(common) >= 2:
            est = np.stack([reg.T_world_scan[n] for n in common])
            tru = np.stack([np.asarray(truth[n]) for n in common])
            err = pose_errors(est, tru)
            reg.truth_errors = {
                "scans": common,
                "rotation_deg": err.rotation_deg.tolist(),
                "translation": err.translation.tolist(),
                **err.summary(),
            }


def _graph_overlap(reg, idx, results, thresh: float, max_points: int = 2000) -> dict:
    partners: dict[int, set[int]] = {}
    for r in results:
        if r.accepted:
            partners.setdefault(r.i, set()).add(r.j)
            partners.setdefault(r.j, set()).add(r.i)
    rng = np.random.default_rng(reg.config.seed)
    registered = {idx[n] for n in reg.T_world_scan}
    world = {}

    def in_world(k: int) -> np.ndarray:
        if k not in world:
            p = reg.scans[k].points
            if len(p) > max_points:
                p = p[rng.choice(len(p), max_points, replace=False)]
            world[k] = transform_points(reg.T_world_scan[reg.scan_names[k]], p)
        return world[k]

    all_d, per_scan, total = [], [], 0
    for k in range(len(reg.scans)):
        others = [o for o in sorted(partners.get(k, ())) if o in registered]
        if k not in registered or not others:
            per_scan.append(None)
            continue
        q = in_world(k)
        d, _ = cKDTree(np.vstack([in_world(o) for o in others])).query(
            q, distance_upper_bound=thresh
        )
        ok = np.isfinite(d)
        total += len(q)
        all_d.append(d[ok])
        per_scan.append(float(np.median(d[ok])) if np.any(ok) else None)
    d = np.concatenate(all_d) if all_d else np.zeros(0)
    return {
        "median": float(np.median(d)) if d.size else None,
        "mean": float(np.mean(d)) if d.size else None,
        "overlap_fraction": float(d.size / max(total, 1)),
        "max_distance": float(thresh),
        "per_scan_median": per_scan,
        "compared_with": "partners in accepted pairs",
    }


def end_to_start_error(T_first: np.ndarray, T_last: np.ndarray, T_first_last_ref: np.ndarray):
    """Position (data units) and rotation (degrees) error of the last scan seen from the
    first: ``inv(T_first) @ T_last`` against the reference ``T_first_last_ref`` (4, 4)."""
    rel = invert_transform(T_first) @ T_last
    err = invert_transform(T_first_last_ref) @ rel
    return (
        float(np.linalg.norm(rel[:3, 3] - T_first_last_ref[:3, 3])),
        float(rotation_angle_deg(err[:3, :3])),
    )


def _drift(reg: SequenceRegistration, results, truth) -> dict:
    """KISS-ICP's drift and what the global solve leaves (see the module docstring)."""
    names = reg.scan_names
    odo = reg.T_odom_scan
    registered = [n for n in names if n in reg.T_world_scan]
    out: dict = {}
    steps = np.diff(np.stack([odo[n][:3, 3] for n in names]), axis=0)
    out["odometry_path_length"] = float(np.sum(np.linalg.norm(steps, axis=1)))
    if len(registered) >= 2:
        first, last = registered[0], registered[-1]
        out["first"], out["last"] = first, last
        if truth and first in truth and last in truth:
            ref = invert_transform(np.asarray(truth[first])) @ np.asarray(truth[last])
            t_path = np.stack([np.asarray(truth[n])[:3, 3] for n in names if n in truth])
            out["truth_path_length"] = float(
                np.sum(np.linalg.norm(np.diff(t_path, axis=0), axis=1))
            )
            e_o, r_o = end_to_start_error(odo[first], odo[last], ref)
            e_g, r_g = end_to_start_error(reg.T_world_scan[first], reg.T_world_scan[last], ref)
            out |= {
                "odometry_end_to_start_vs_truth": e_o,
                "odometry_end_to_start_rotation_deg_vs_truth": r_o,
                "global_end_to_start_vs_truth": e_g,
                "global_end_to_start_rotation_deg_vs_truth": r_g,
                "reduction_vs_truth": e_o / e_g if e_g > 0 else float("inf"),
            }
            common = [n for n in names if n in truth]
            err = pose_errors(
                np.stack([odo[n] for n in common]), np.stack([np.asarray(truth[n]) for n in common])
            )
            out["odometry_vs_truth"] = err.summary()
    # A verified loop closure joining the end of the sequence to its start.
    m = len(names)
    margin = max(1, m // 10)
    closing = [
        r
        for r in results
        if r.accepted and r.stats.get("kind") == "loop" and r.i < margin and r.j >= m - margin
    ]
    out["closed_loop"] = bool(closing)
    if closing:
        r = min(closing, key=lambda r: r.i + (m - 1 - r.j))
        a, b = names[r.i], names[r.j]
        out["loop_pair"] = [a, b]
        e_o, r_o = end_to_start_error(odo[a], odo[b], r.T_i_j)
        out["odometry_end_to_start_vs_loop_closure"] = e_o
        out["odometry_end_to_start_rotation_deg_vs_loop_closure"] = r_o
        if a in reg.T_world_scan and b in reg.T_world_scan:
            e_g, r_g = end_to_start_error(reg.T_world_scan[a], reg.T_world_scan[b], r.T_i_j)
            out["global_end_to_start_vs_loop_closure"] = e_g
            out["global_end_to_start_rotation_deg_vs_loop_closure"] = r_g
    return out


def _sequence_report(
    reg, seq, odom: Odometry, time_source, gaps, results, loops: LoopClosures, noise, truth,
    warnings,
) -> dict:  # fmt: skip
    names = reg.scan_names
    by_kind: dict[str, dict] = {}
    for r in results:
        k = by_kind.setdefault(
            r.stats.get("kind", ""),
            {"tried": 0, "accepted": 0, "feature_ransac": 0, "accepted_from": {}, "rejected": []},
        )
        k["tried"] += 1
        if r.accepted:
            k["accepted"] += 1
            init = r.stats.get("init", "")
            k["feature_ransac"] += init == "feature RANSAC"
            k["accepted_from"][init] = k["accepted_from"].get(init, 0) + 1
        else:
            k["rejected"].append(list(r.names))
    for g in gaps:
        g["after"], g["before"] = names[g["after"]], names[g["after"] + 1]
    loop_stats = by_kind.get("loop", {"tried": 0, "accepted": 0})
    return {
        "timestamp_source": time_source,
        "gaps": gaps,
        "odometry": {
            "backend": "kiss-icp",
            "version": _kiss_version(),
            "max_range": odom.max_range,
            "voxel_size": odom.voxel_size,
            "seconds": odom.seconds,
            "config": odom.config,
        },
        "settings": seq.model_dump(mode="json"),
        "residual_reference": noise,
        "pairs_by_kind": by_kind,
        "loop_closures": {
            "radius": loops.radius,
            "candidates": len(loops.candidates),
            "accepted": loop_stats["accepted"],
        },
        "drift": _drift(reg, results, truth),
        "warnings": warnings,
    }


def _kiss_version() -> str | None:
    try:
        from importlib.metadata import version

        return version("kiss-icp")
    except Exception:  # metadata missing: report no version rather than fail
        return None
