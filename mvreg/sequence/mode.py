"""register_sequence(): ordered range scans (a moving LiDAR) in, globally aligned poses out.

The same pipeline as ``register`` (:func:`mvreg.pipeline.register.run_pipeline`) with the
sequence mode: timestamps and gaps -> KISS-ICP odometry -> range-scan preprocessing
(normals towards the sensor) -> consecutive and skip pairs from the odometry, each
verified by ICP -> loop closures where the chained poses come back -> the global stage
with pose tracks -> evaluation and the drift report.

A scan is a set of points in its sensor frame (the sensor at the origin); files are taken
in natural order of their names. A scan that no accepted pair connects to the rest is
listed in ``unregistered``, never given a pose made up from the odometry. Design notes
and measurements: docs/design/sequence.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mvreg.config import RegisterConfig, load_config
from mvreg.config.sequence import SequenceConfig
from mvreg.errors import ConfigError
from mvreg.pairwise import derive_scales, with_noise
from mvreg.pipeline.register import run_pipeline
from mvreg.pipeline.result import Registration
from mvreg.pipeline.run import Run
from mvreg.pipeline.stages import PairGraph
from mvreg.sequence.loops import loop_closures
from mvreg.sequence.odometry import kiss_icp_odometry
from mvreg.sequence.pairs import chain_poses, sequential_results
from mvreg.sequence.preprocess import preprocess_range_scan
from mvreg.sequence.report import evaluate_sequence, sequence_report
from mvreg.sequence.sources import read_dataloader
from mvreg.sequence.timestamps import find_gaps, sequence_timestamps
from mvreg.sequence.tracks import PoseGraphPlan


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


def sequence_columns(r) -> dict:
    return {"kind": r.stats.get("kind", ""), "init": r.stats.get("init", "")}


class SequenceMode:
    """Ordered range scans: odometry, sequential pairs and loop closures."""

    what = "a sequence"

    def __init__(self, folder: Path | None, timestamps: Sequence[float] | None = None):
        self.folder = folder
        self.given_times = timestamps
        self.warnings: list[str] = []

    def preprocess(self, run: Run, scans):
        seq = run.cfg.sequence
        self.times, self.time_source = sequence_timestamps(
            scans, self.folder, self.given_times, self.warnings
        )
        self.gaps = find_gaps(self.times, seq.gap_factor)
        run.progress.stage("odometry", len(scans))
        self.odom = kiss_icp_odometry(
            [s.points for s in scans], self.times, seq, advance=run.progress.advance
        )
        run.timed("odometry")
        scales = derive_scales(scans, run.cfg.preprocess, run.executor)
        run.progress.stage("preprocess", len(scans))
        pre = []
        for s in scans:
            pre.append(preprocess_range_scan(s, scales.voxel, run.cfg.preprocess, seq))
            run.progress.advance()
        return with_noise(scales, pre), pre

    def pair_graph(self, run: Run, scans, pre, scales) -> PairGraph:
        cfg, prog = run.cfg, run.progress
        results, self.noise = sequential_results(
            pre, self.odom, self.times, cfg, cfg.sequence, prog
        )
        if self.noise is None:
            self.warnings.append(
                "no consecutive scans are in contact: residual scale not calibrated"
            )
        run.timed("sequential_pairs")
        self.loops = loop_closures(
            pre, scans, chain_poses(self.odom.T_odom_scan, results), results, cfg,
            cfg.sequence, prog,
        )  # fmt: skip
        results += self.loops.results
        run.timed("loop_closures")
        return PairGraph(results, PoseGraphPlan(), columns=sequence_columns)

    def evaluate(self, run: Run, reg, pre, results, truth) -> None:
        names = reg.scan_names
        reg.timestamps = dict(zip(names, self.times.tolist(), strict=True))
        reg.T_odom_scan = dict(zip(names, self.odom.T_odom_scan, strict=True))
        evaluate_sequence(reg, pre, results, truth)
        reg.sequence = sequence_report(
            reg, run.cfg.sequence, self.odom, self.time_source, self.gaps, results,
            self.loops, self.noise, truth, self.warnings,
        )  # fmt: skip


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
        config: a RegisterConfig (its ``sequence`` section sets the sequence stages;
            default: the defaults); ``overrides`` apply on top of it (dotted keys, e.g.
            ``**{"sequence.skip_pairs": 2}``).
        sequence: a SequenceConfig replacing the config's ``sequence`` section.
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
    if config is not None and overrides:
        raise ConfigError(f"give either a config or overrides, not both ({', '.join(overrides)})")
    # Overrides apply on top of a given configuration too (``config=cfg, seed=1``).
    cfg = config if config is not None and not overrides else load_config(base=config, **overrides)
    if sequence is not None:
        cfg = cfg.model_copy(update={"sequence": sequence})
    folder = Path(source) if isinstance(source, (str, Path)) else None
    sq = cfg.sequence
    read_warnings: list[str] = []
    if sq.dataloader is not None:
        if folder is None:
            raise ConfigError("sequence.dataloader reads a path, not point arrays")
        source, names = read_dataloader(
            sq.dataloader, folder, sq.dataloader_sequence, sq.dataloader_max_frames,
            warnings=read_warnings,
        )  # fmt: skip
        folder = None  # frames, not scan files: no timestamps.txt or ground_truth.json
    mode = SequenceMode(folder, timestamps)
    mode.warnings.extend(read_warnings)
    with Run(cfg, recorder, progress) as run:
        return run_pipeline(run, mode, source, names, truth, result_type=SequenceRegistration)
