"""KISS-Matcher as the pairwise front end of mvreg's global stage (issue 13, item 4).

KISS-Matcher (Lim et al., ICRA 2025; ``pip install kiss-matcher``) proposes each pair's
relative pose from Faster-PFH matches pruned by graph-theoretic outlier rejection
(ROBIN) and a GNC-TLS solver, without RANSAC. Here it replaces mvreg's FPFH + RANSAC
proposal and nothing else: every candidate pair is proposed by KISS-Matcher, then
refined and decided exactly as mvreg decides its own proposals (feature-level ICP, the
acceptance rule, fine ICP: :func:`mvreg.pairwise.decision.verify`), and the accepted
pairs go through mvreg's global stage unchanged (tracks, REG-ADMM, robust rounds,
refinement, verification and placement of leftovers). mvreg's own recovery of pairs
(the retry from stored poses and the rotation search for unconnected scans) is part of
mvreg's front end and is left out, so the row measures the front end.

Settings: ``voxel_size`` = mvreg's feature voxel of the run (what KISS-Matcher's voxel is
for: the scale of its normals (3 voxels) and descriptors (5 voxels)); everything else at
KISS-Matcher's defaults; the points are scaled so that this voxel is KISS-Matcher's own 0.3
(:func:`kiss_matcher_pose`). A small sweep on builtin scans, not on the benchmark's meshes
(``mvreg synth builtin --views 10 --placement sphere --noise 0.002 --random-frames``; pairs
overlapping >= 0.3; KISS-Matcher's rotation within 5 deg of the truth, before any ICP;
measured on the unscaled points, whose voxels, 0.0205 and 0.03, it accepts):

| setting | seed 0, ~20k points: 22 pairs | seed 1, ~3k points: 21 pairs |
| --- | --- | --- |
| defaults at mvreg's voxel (kept) | 6 | 0 |
| voxel x0.5 | 3 | 4 |
| noise-bound gains 2 / 1.5 | 5 | 2 |
| noise-bound gains 3 / 2 | 4 | 1 |
| linearity threshold 0.5 | 3 | 3 |
| voxel x0.5, gains 2 / 1.5 | 3 | 2 |
| voxel x0.5, gains 3 / 2 | 3 | 1 |

No setting was better on both resolutions. The kept setting on the scaled points, as
:func:`kiss_matcher_pose` runs it: 7 and 2 (KISS-Matcher is not exactly scale-invariant).
"""

from __future__ import annotations

import time

import numpy as np

from mvreg.executor import single_threaded_blas
from mvreg.pairwise import align_pairs, candidate_pairs
from mvreg.pairwise.aligners.base import ALIGNERS, BaseAligner, register_aligner
from mvreg.pairwise.decision import verify
from mvreg.pairwise.result import pair_result
from mvreg.pipeline import PairGraph, Run, run_pipeline
from mvreg.pipeline.stages import MultiviewPlan, UnorderedMode, free_space_columns

NAME = "kiss-matcher"
KISS_VOXEL = 0.3  # KISS-Matcher's default voxel; the data are scaled to it


def kiss_matcher_pose(
    source: np.ndarray, target: np.ndarray, voxel: float
) -> tuple[np.ndarray, dict]:
    """(T_target_source (4, 4), stats) from KISS-Matcher on two (N, 3) point arrays.

    KISS-Matcher refuses voxels below its LiDAR-sized minimum, so the points are scaled
    to make ``voxel`` its default 0.3 (its thresholds are all in voxels; the rotation does
    not change, the translation is scaled back)."""
    import kiss_matcher as km

    scale = KISS_VOXEL / float(voxel)
    matcher = km.KISSMatcher(km.KISSMatcherConfig(voxel_size=KISS_VOXEL))
    sol = matcher.estimate(
        np.ascontiguousarray(source * scale, dtype=np.float64),
        np.ascontiguousarray(target * scale, dtype=np.float64),
    )
    T = np.eye(4)
    T[:3, :3] = np.asarray(sol.rotation, dtype=np.float64)
    T[:3, 3] = np.asarray(sol.translation, dtype=np.float64).ravel() / scale
    stats = {
        "kiss_valid": bool(sol.valid),
        "kiss_rotation_inliers": int(matcher.get_num_rotation_inliers()),
        "kiss_final_inliers": int(matcher.get_num_final_inliers()),
    }
    return T, stats


class KissMatcherAligner(BaseAligner):
    """KISS-Matcher's proposal, mvreg's ICP and acceptance rule (module docstring)."""

    def align(self, pre_i, pre_j, guess=None, seed=0, *, i=0, j=1):
        start, scales = time.perf_counter(), self.scales_for(pre_i)
        T0, stats = kiss_matcher_pose(pre_j.fine_points, pre_i.fine_points, scales.voxel)
        if not stats["kiss_valid"]:
            return pair_result(pre_i, pre_j, i, j, T0, "KISS-Matcher found no solution", None,
                               stats, start, fine_voxel=scales.fine_voxel)  # fmt: skip
        with single_threaded_blas():
            v = verify(pre_i, pre_j, T0, self.cfg, scales)
        return pair_result(pre_i, pre_j, i, j, v.T, v.reason, v.scores, stats, start,
                           fine_voxel=scales.fine_voxel)  # fmt: skip


if NAME not in ALIGNERS:
    register_aligner(NAME)(KissMatcherAligner)


class KissMode(UnorderedMode):
    """mvreg's unordered mode with KISS-Matcher proposing every candidate pair."""

    def pair_graph(self, run: Run, scans, pre, scales) -> PairGraph:
        cfg = run.cfg
        pairs = candidate_pairs(pre, cfg.pairs)
        run.progress.stage("pairs", len(pairs))
        results = align_pairs(
            pre, pairs, cfg.align, cfg.seed, progress=lambda _r: run.progress.advance(),
            executor=run.executor, scales=scales, method=NAME,
        )  # fmt: skip
        run.timed("pairwise")
        return PairGraph(results, MultiviewPlan(), columns=free_space_columns)


def run_kiss_mvreg(folder, seed: int = 0, truth=None):
    """mvreg's pipeline on ``folder`` with the KISS-Matcher front end: the Registration
    (its ``T_world_scan`` holds the verified scans only, as ``register``'s does)."""
    from mvreg.config import load_config

    return run_pipeline(Run(load_config(seed=seed)), KissMode(), folder, truth=truth)
