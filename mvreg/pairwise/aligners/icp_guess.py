"""``icp-guess``: point-to-plane ICP of scan j onto scan i from a given pose, scored.

For pairs whose relative pose is roughly known (an odometry step, a pose chained along
a sequence, global poses to refine): feature-level ICP
(``icp_coarse_distance_voxels``), then fine-level ICP (``icp_fine_distance_voxels``),
as :func:`~mvreg.pairwise.decision.verify` does after RANSAC, but without the coarse
gate: the fine result is always scored and decided by the shared acceptance rule
(:func:`~mvreg.pairwise.decision.rescore`). ``guess`` None means identity.
Deterministic (no random choices; ``seed`` unused). Stats: ``init`` ("odometry"; callers
relabel it), ``T_guess`` (the guess as nested lists), ``median_residual``.
"""

from __future__ import annotations

import time

import numpy as np

from mvreg.executor import single_threaded_blas
from mvreg.pairwise.aligners.base import BaseAligner, register_aligner
from mvreg.pairwise.decision import rescore
from mvreg.pairwise.icp import coarse_icp, fine_icp
from mvreg.pairwise.result import PairResult


@register_aligner("icp-guess")
class IcpGuessAligner(BaseAligner):
    """ICP from a guess, then the acceptance rule (module docstring)."""

    def align(self, pre_i, pre_j, guess=None, seed=0, *, i=0, j=1) -> PairResult:
        """ICP of scan j onto scan i from ``guess`` (T_i_j, (4, 4); None: identity)."""
        cfg = self.cfg
        start = time.perf_counter()
        scales = self.scales_for(pre_i)
        guess = np.eye(4) if guess is None else guess
        with single_threaded_blas():
            T = coarse_icp(pre_i, pre_j, guess, cfg, scales.voxel)
            T = fine_icp(pre_i, pre_j, T, cfg.icp_fine_distance_voxels, cfg, scales.voxel)
        res = PairResult(
            i=i,
            j=j,
            T_i_j=T,
            overlap_ratio=0.0,
            inlier_rmse=float("inf"),
            num_correspondences=0,
            fitness=0.0,
            accepted=False,
            reason="not scored",
            names=(pre_i.name, pre_j.name),
            stats={"init": "odometry", "T_guess": np.asarray(guess).tolist()},
        )
        rescore(res, pre_i, pre_j, cfg, scales=scales)
        res.seconds = time.perf_counter() - start
        return res
