"""The stages of a run that every mode shares, and the contract of a mode.

A *mode* says how scans become a pair graph: :class:`UnorderedMode` (candidate pairs,
feature RANSAC alignment, rejected pairs retried from the poses stored in the files
(:mod:`mvreg.pairwise.stored_poses`), rotation search for scans left unconnected; the
default) or
the sequence mode of :mod:`mvreg.sequence` (odometry and loop closures). Everything
else -- loading, the global stage, evaluation, the result -- is the same pipeline
(:func:`mvreg.pipeline.register.run_pipeline`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from mvreg.globalstage.stage import MultiviewPlan, TrackPlan
from mvreg.pairwise import (
    PairResult,
    PreprocessedScan,
    align_pairs,
    candidate_pairs,
    derive_scales,
    preprocess_all,
    with_noise,
)
from mvreg.pairwise.joint import choose_jointly
from mvreg.pairwise.search import confirm_weak_scans, connect_unconnected
from mvreg.pairwise.stored_poses import retry_from_stored_poses
from mvreg.pipeline.run import Run
from mvreg.scales import Scales


@dataclass
class PairGraph:
    """What a pair-graph stage produced: the pair results (accepted or not), the plan the
    global stage follows with them, extra pair-table columns, and mode-specific data."""

    results: list[PairResult]
    plan: TrackPlan
    columns: Callable[[PairResult], dict] | None = None
    extra: dict = field(default_factory=dict)


class Mode(Protocol):
    """A kind of input: how scans are preprocessed and paired, and how the run is
    evaluated. ``what`` names the input in messages ("registration", "a sequence")."""

    what: str

    def preprocess(self, run: Run, scans) -> tuple[Scales, list[PreprocessedScan]]: ...

    def pair_graph(self, run: Run, scans, pre, scales: Scales) -> PairGraph: ...

    def evaluate(self, run: Run, reg, pre, results, truth) -> None:
        """Fill ``reg.overlap``, ``reg.truth_errors`` (and mode extras) in place."""


def free_space_columns(r: PairResult) -> dict:
    """The view tests' scores, and ``init`` for a pose not from features ("stored poses")."""
    extra = {"init": r.stats["init"]} if r.stats.get("init") == "stored poses" else {}
    return {
        "free_space_violation": r.free_space_violation,
        "unseen_violation": r.unseen_violation,
    } | extra


class UnorderedMode:
    """Scans in no particular order (the default of ``register``)."""

    what = "registration"

    def __init__(self, pair_hook=None):
        self.pair_hook = pair_hook

    def preprocess(self, run: Run, scans):
        cfg = run.cfg.preprocess
        scales = derive_scales(scans, cfg, run.executor)
        run.progress.stage("preprocess", len(scans))
        pre = preprocess_all(
            scans, scales.voxel, cfg, run.executor, progress=lambda _p: run.progress.advance()
        )
        return with_noise(scales, pre), pre

    def pair_graph(self, run: Run, scans, pre, scales: Scales) -> PairGraph:
        cfg = run.cfg
        pairs = candidate_pairs(pre, cfg.pairs)
        run.progress.stage("pairs", len(pairs))
        results = align_pairs(
            pre, pairs, cfg.align, cfg.seed, progress=lambda _r: run.progress.advance(),
            executor=run.executor, scales=scales,
        )  # fmt: skip
        results = retry_from_stored_poses(pre, scans, results, cfg.align, scales)
        results = connect_unconnected(
            pre, results, cfg.align, cfg.search, executor=run.local, scales=scales
        )  # the rotation search stays in-process (one scan at a time)
        if self.pair_hook is not None:
            results = self.pair_hook(pre, results)
        run.timed("pairwise")
        return PairGraph(results, MultiviewPlan(), columns=free_space_columns)

    def recover(self, run: Run, pre, scales: Scales, results, out, verification, dropped):
        """Pair results for further passes (a list of choices), or None when nothing
        changed. The scans the first pass (``out``, ``verification``, ``dropped``)
        neither verified nor found undetermined (a symmetry more pairs cannot settle)
        get their pairs searched again: with ``search.joint`` (runs of at most
        ``search.joint_max_scans`` scans), several hypotheses per pair chosen jointly,
        the verified scans as anchors (:mod:`mvreg.pairwise.joint`); else with
        ``search.weak_scans``, :func:`mvreg.pairwise.search.confirm_weak_scans`. A run
        whose scans were all verified never gets here."""
        cfg = run.cfg
        done = {s for s, v in verification.items() if v.status in ("verified", "undetermined")}
        todo = [s for s in range(len(pre)) if s not in done]
        if not todo or not cfg.search.enabled:
            return None
        if cfg.search.joint and len(pre) <= cfg.search.joint_max_scans:
            poses = {} if out.solution is None else out.T_world_scan
            anchors = {
                s: T for s, T in poses.items()
                if s not in dropped and s in verification and verification[s].status == "verified"
            }  # fmt: skip
            choices = choose_jointly(
                pre, results, todo, anchors, cfg.align, cfg.search, run.local, scales,
                cfg.robust.cycle_check_voxels or 2.0,
            )  # fmt: skip
            run.timed("joint_choice")
        elif cfg.search.weak_scans:
            choices = [confirm_weak_scans(
                pre, results, cfg.align, cfg.search, executor=run.local, scales=scales,
                max_voxels=cfg.robust.cycle_check_voxels or 2.0, only=todo,
            )]  # fmt: skip
            run.timed("weak_scan_search")
        else:
            return None
        out, seen = [], set()
        for new in choices:
            key = tuple((r.i, r.j, r.accepted, r.T_i_j.tobytes()) for r in new)
            if key not in seen and not all(a is b for a, b in zip(new, results, strict=True)):
                out.append(new)
            seen.add(key)
        return out or None

    def evaluate(self, run: Run, reg, pre, results, truth) -> None:
        from mvreg.pipeline.evaluate import evaluate_overlap_and_truth

        evaluate_overlap_and_truth(reg, pre, truth)
