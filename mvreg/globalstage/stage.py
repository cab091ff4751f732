"""The global stage as one step of the pipeline: pair results in, poses out.

    tracks -> global solve (certified) -> robust re-weighting -> refinement
    -> joint point-to-plane ICP -> final check

:class:`GlobalStage` runs that list for any pair graph; *how* tracks are made and refined
is the :class:`TrackPlan` the pair-graph stage chooses (multiview tracks and ICP rounds
for unordered scans, :class:`MultiviewPlan`; pose tracks for sequences, in
:mod:`mvreg.sequence`). Takes the preprocessed scans and pair results; returns a
:class:`GlobalOutcome` whose solution holds a pose for every scan the accepted pairs
connect to the first registered scan (None when no track links two scans).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np

from mvreg.config import RegisterConfig
from mvreg.executor import Executor
from mvreg.globalstage.joint_icp import joint_icp
from mvreg.globalstage.place import LeftoverSearches, place_leftovers
from mvreg.globalstage.probes import resting_on_open_partners
from mvreg.globalstage.refine import prepare_dense_levels, refine_rounds
from mvreg.globalstage.robust import cycle_check, final_check, robust_rounds
from mvreg.globalstage.solve import GlobalSolution, TrackSolver
from mvreg.globalstage.verify import verify_and_resolve
from mvreg.pairwise import PairResult, PreprocessedScan, Tracks, build_tracks


@dataclass
class GlobalOutcome:
    """What the global stage produced.

    solution: poses and the last solve (None: no two scans linked); tracks: the last
    tracks; weights: (P,) final weight of each of ``tracks.pairs``; results: the pair
    results (a plan may replace re-aligned pairs); robust_log / refine_log: per round;
    joint_icp: the joint ICP's log (None when it did not run).
    """

    solution: GlobalSolution | None
    tracks: Tracks
    weights: np.ndarray
    results: list[PairResult]
    robust_log: list[dict] = field(default_factory=list)
    refine_log: list[dict] = field(default_factory=list)
    joint_icp: dict | None = None

    @property
    def T_world_scan(self) -> dict[int, np.ndarray]:
        return {} if self.solution is None else self.solution.T_world_scan

    @property
    def pair_weight(self) -> dict[tuple[int, int], float]:
        """{(i, j): final weight} of every pair of the last tracks."""
        pairs_w = zip(self.tracks.pairs, self.weights, strict=True)
        return {(int(i), int(j)): float(w) for (i, j), w in pairs_w}


@dataclass
class GlobalContext:
    """Plain values the plans and the stage share: sections, lengths, workers."""

    cfg: RegisterConfig
    voxel: float
    executor: Executor
    solver: TrackSolver
    scans: Sequence | None = None
    dense: Future | None = None


class TrackPlan(Protocol):
    """How tracks are built from the pair results and refined (one per pair-graph kind)."""

    final_check: bool
    model_search: bool  # verification searches the model of the others (second poses, leftovers)

    def prepare(self, ctx: GlobalContext, pre) -> None:
        """Start work that needs no poses (runs while the first solve does)."""

    def initial_weights(self, ctx: GlobalContext, pre, results) -> tuple[np.ndarray | None, list]:
        """Weights (A,) of the accepted pairs before the first solve, and a log."""

    def tracks(self, ctx: GlobalContext, pre, results, weights) -> Tracks: ...

    def refine(self, ctx: GlobalContext, pre, out: GlobalOutcome) -> None:
        """Refine ``out.solution`` in place of ``out`` (its tracks, weights, results, log)."""

    def joint_icp_scope(self, ctx: GlobalContext, out: GlobalOutcome) -> tuple:
        """(pairs or None, levels or None, min_normal_cos) for the joint ICP."""


class GlobalStage:
    """Runs the global stage with a plan; ``progress`` and ``timed`` come from the run.

    :meth:`run_verified` then verifies every scan's pose (:mod:`mvreg.globalstage.verify`)
    and runs the stage again without the pairs of the scans that fail."""

    def __init__(self, plan: TrackPlan):
        self.plan = plan
        # The leftovers searched in vain, kept across the passes of the run.
        self.searched = LeftoverSearches()

    def run(
        self,
        ctx: GlobalContext,
        pre: Sequence[PreprocessedScan],
        results: list[PairResult],
        progress,
        timed: Callable[[str], None],
    ) -> GlobalOutcome:
        plan, cfg = self.plan, ctx.cfg
        plan.prepare(ctx, pre)
        w0, robust_log = plan.initial_weights(ctx, pre, results)
        tracks = plan.tracks(ctx, pre, results, w0)
        out = GlobalOutcome(None, tracks, np.zeros(len(tracks.pairs)), list(results), robust_log)
        if tracks.problem is None:
            return out
        sol = ctx.solver(tracks)
        timed("tracks_and_solve")
        progress.stage("robust re-weighting")
        sol, out.weights, log = robust_rounds(
            tracks, sol, ctx.voxel, cfg.robust, ctx.solver, weights=w0
        )
        out.robust_log += log
        timed("robust")
        progress.stage("refinement", cfg.refine.rounds)
        out.solution = sol
        plan.refine(ctx, pre, out)
        if cfg.refine.rounds:
            pairs, levels, min_cos = plan.joint_icp_scope(ctx, out)
            out.solution, out.joint_icp = joint_icp(
                pre, out.solution, cfg.refine, cfg.robust, min_cos, ctx.voxel, ctx.executor,
                levels=levels, pairs=pairs,
            )  # fmt: skip
            if plan.final_check:
                out.weights, log = final_check(
                    pre, out.results, out.tracks, out.weights, out.solution, ctx.voxel, cfg.robust
                )
                out.robust_log += [log] if log is not None else []
        timed("refine")
        return out

    def run_verified(self, ctx, pre, results, progress, timed):
        """:meth:`run`, then verification: (outcome, {scan: ScanVerification} of every
        scan that had a pose, the dropped scan indices). A dropped scan gets no pose."""
        out = self.run(ctx, pre, results, progress, timed)
        progress.stage("verification")

        def resolve(kept):
            timed("verify")  # the round that dropped scans, before the stages run again
            return self.run(ctx, pre, kept, progress, timed)

        out, ver, dropped, groups = verify_and_resolve(
            pre, results, out, resolve, ctx.voxel, ctx.cfg.align,
            discrete=self.plan.model_search, executor=ctx.executor,
        )  # fmt: skip
        timed("verify")
        if self.plan.model_search and out.solution is not None:
            verified = {s: T for s, T in out.T_world_scan.items() if s not in dropped}
            todo = [s for s in range(len(pre)) if s not in verified and _worth_placing(ver.get(s))]
            placed = place_leftovers(
                pre, verified, todo, ctx.voxel, ctx.cfg.align, results, groups=groups,
                searched=self.searched,
            )  # fmt: skip
            for s, (T, v) in placed.items():
                out.solution.T_world_scan[s] = T
                ver[s] = v
                dropped = [d for d in dropped if d != s]
            timed("place_leftovers")
            if placed and self.plan.final_check:
                self._polish(ctx, pre, out, dropped)
                timed("polish")
        # The statuses as they ended: a search or a drop after a scan's last check may
        # leave it resting on partners whose poses are no longer verified.
        dropped = sorted({*dropped, *resting_on_open_partners(ver, [p.name for p in pre])})
        out.results = _every_pair(results, out.results)
        return out, ver, dropped

    def _polish(self, ctx, pre, out, dropped) -> None:
        """Joint ICP over the verified scans once leftovers were placed: a placed scan's
        pose comes from ICP on the model alone, and the scans solved before it never saw
        it (a leaf scan of a planar part held by one pair, 3 deg off, is set by the placed
        scans that overlap it). Kept on joint ICP's own terms: no scan moved further than
        ``refine.joint_icp_max_move_voxels`` (below the one-voxel tolerance the scans were
        verified at)."""
        keep = {s: T for s, T in out.T_world_scan.items() if s not in dropped}
        sol = replace(out.solution, T_world_scan=dict(keep))
        pairs, levels, min_cos = self.plan.joint_icp_scope(ctx, out)
        new, log = joint_icp(
            pre, sol, ctx.cfg.refine, ctx.cfg.robust, min_cos, ctx.voxel, ctx.executor,
            levels=levels, pairs=pairs,
        )  # fmt: skip
        if log is not None and log.get("accepted"):
            out.solution.T_world_scan.update(new.T_world_scan)


def _every_pair(results: Sequence[PairResult], last: Sequence[PairResult]) -> list[PairResult]:
    """Every pair result of the run (the pair table reports them all), each as the last
    solve saw it: verification re-solves without the pairs of dropped scans, so the last
    outcome holds only a subset."""
    latest = {(r.i, r.j): r for r in last}
    seen = {(r.i, r.j) for r in results}
    return [latest.get((r.i, r.j), r) for r in results] + [
        r for r in last if (r.i, r.j) not in seen
    ]


def _worth_placing(v) -> bool:
    """A scan without a verified pose is searched against the model unless the data were
    found not to fix its pose (a second search would find the same ambiguity)."""
    return v is None or v.status != "undetermined"


class MultiviewPlan:
    """Unordered scans: the cycle check, tracks of mutual nearest neighbours over every
    accepted pair, multiview ICP rounds (the last on the dense level), final check."""

    final_check = True
    model_search = True

    def prepare(self, ctx, pre):
        """Resample the raw scans for the last refinement round in the background."""
        ctx.dense = prepare_dense_levels(
            ctx.scans, pre, ctx.cfg.refine, ctx.voxel, ctx.executor.workers
        )

    def initial_weights(self, ctx, pre, results):
        return cycle_check(pre, results, ctx.cfg.robust, ctx.cfg.align)

    def tracks(self, ctx, pre, results, weights):
        return build_tracks(
            pre, results, ctx.cfg.tracks, pair_weights=weights, executor=ctx.executor
        )

    def refine(self, ctx, pre, out):
        out.solution, out.refine_log = refine_rounds(
            pre, out.solution, ctx.cfg.refine, ctx.cfg.robust, ctx.cfg.tracks, ctx.voxel,
            ctx.solver, ctx.executor, scans=ctx.scans, dense=ctx.dense,
        )  # fmt: skip

    def joint_icp_scope(self, ctx, out):
        levels = ctx.dense.result() if ctx.dense is not None else None
        return None, levels, ctx.cfg.tracks.min_normal_cos
