"""The global stage of a sequence: tracks that carry each accepted pair's pose (a pose
graph in REG form, :func:`pose_tracks`) and refinement that re-aligns the pairs the
solution disagrees with (:func:`refine_pose_graph`), as a
:class:`~mvreg.globalstage.stage.TrackPlan` (:class:`PoseGraphPlan`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from mvreg.config import RegisterConfig
from mvreg.config.sequence import SequenceConfig
from mvreg.config.tracks import TracksConfig
from mvreg.executor import single_threaded_blas
from mvreg.geometry import invert_transform, transform_points
from mvreg.globalstage.refine import refine_rounds
from mvreg.globalstage.robust import pair_residuals, robust_weights
from mvreg.globalstage.solve import GlobalSolution, max_translation_change
from mvreg.pairwise import fine_icp, rescore
from mvreg.pairwise.preprocess import PreprocessedScan
from mvreg.pairwise.result import PairResult
from mvreg.pairwise.tracks import Tracks, build_tracks, tracks_from_correspondences
from mvreg.sequence.pairs import threads_map

# Refinement re-aligns a pair whose points lie this many voxels apart under the global poses.

REFINE_DISAGREEMENT_VOXELS = 0.1


def sequence_tracks_config(tracks: TracksConfig, seq: SequenceConfig) -> TracksConfig:
    """The tracks section with the sequence's defaults where the user set none."""
    update = {}
    if tracks.max_correspondences_per_pair is None:
        update["max_correspondences_per_pair"] = seq.correspondences_per_pair
    if "min_normal_cos" not in tracks.model_fields_set:
        update["min_normal_cos"] = seq.min_normal_cos
    return tracks.model_copy(update=update)


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
    honours every pair's ICP (point-to-plane) alignment as far as the loops allow. Why
    not mutual nearest neighbours: docs/design/sequence.md.
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
    solver,
) -> tuple[GlobalSolution, Tracks, np.ndarray, list[PairResult], list[dict]]:
    """Refinement rounds for :func:`pose_tracks`: re-align the pairs the solution disagrees with.

    A pair whose linked points lie more than ``REFINE_DISAGREEMENT_VOXELS`` (0.1) voxels
    apart (median) under the global poses -- typically a loop closure whose ICP started
    from a drifted odometry guess and stopped in a nearby minimum -- is aligned again by
    fine point-to-plane ICP started from the global poses (``cfg.align`` distances);
    if still accepted it replaces the pair, and the problem is re-solved warm-started with
    weights from the residuals (``cfg.robust``). At most ``cfg.refine.rounds`` rounds,
    each pair re-aligned at most once; stops when no new pair disagrees; pairs that agree
    are not re-aligned (docs/design/sequence.md).
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
        for n, new in zip(todo, threads_map(run, todo, cfg.threads), strict=True):
            if new.accepted:
                results[n] = new
                changed += 1
        new_tracks = pose_tracks(pre, results, per_pair)
        if new_tracks.problem is None:
            break
        tracks = new_tracks
        weights = robust_weights(pair_residuals(tracks, poses), voxel, cfg.robust)
        prev = sol
        sol = solver(tracks.reweighted(weights), init=poses)
        log.append(
            {
                "round": k + 1,
                "pairs_disagreeing": len(todo),
                "pairs_realigned": changed,
                "pairs_zero_weight": int(np.sum(weights == 0)),
                "max_translation_change": max_translation_change(sol, prev),
                "certified": sol.result.certified,
            }
        )
    return sol, tracks, weights, results, log


class PoseGraphPlan:
    """The global stage of a sequence: no cycle check (odometry pairs are verified one by
    one), :func:`pose_tracks` (or mutual nearest neighbours with
    ``sequence.correspondences="nearest"``), :func:`refine_pose_graph` (or multiview ICP
    rounds over the kept pairs), the joint ICP over the kept pairs, no final check."""

    final_check = False
    # Odometry orders the frames and bounds their motion: no search against the model (it
    # would cost a RANSAC per frame and per bridge of a long chain).
    model_search = False

    def prepare(self, ctx, pre) -> None:
        pass

    def initial_weights(self, ctx, pre, results):
        return None, []

    def _per_pair(self, ctx) -> int:
        tcfg = sequence_tracks_config(ctx.cfg.tracks, ctx.cfg.sequence)
        return tcfg.max_correspondences_per_pair or ctx.cfg.sequence.correspondences_per_pair or 400

    def tracks(self, ctx, pre, results, weights):
        if ctx.cfg.sequence.correspondences == "pose":
            return pose_tracks(pre, results, self._per_pair(ctx))
        return build_tracks(pre, results, sequence_tracks_config(ctx.cfg.tracks, ctx.cfg.sequence))

    def refine(self, ctx, pre, out) -> None:
        cfg = ctx.cfg
        if cfg.sequence.correspondences == "pose":
            out.solution, out.tracks, out.weights, out.results, out.refine_log = refine_pose_graph(
                pre, out.solution, out.tracks, out.results, out.weights, cfg,
                self._per_pair(ctx), ctx.solver,
            )  # fmt: skip
            return
        pairs_w = zip(out.tracks.pairs, out.weights, strict=True)
        graph = [(int(i), int(j)) for (i, j), w in pairs_w if w > 0]
        tcfg = sequence_tracks_config(cfg.tracks, cfg.sequence)
        out.solution, out.refine_log = refine_rounds(
            pre, out.solution, cfg.refine, cfg.robust, tcfg, ctx.voxel,
            ctx.solver, ctx.executor, pairs=graph,
        )  # fmt: skip

    def joint_icp_scope(self, ctx, out):
        pairs_w = zip(out.tracks.pairs, out.weights, strict=True)
        kept = [(int(i), int(j)) for (i, j), w in pairs_w if w > 0]
        return kept, None, sequence_tracks_config(ctx.cfg.tracks, ctx.cfg.sequence).min_normal_cos
