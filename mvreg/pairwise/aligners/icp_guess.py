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
from collections.abc import Sequence

import numpy as np

from mvreg.config.align import AlignConfig, SearchConfig
from mvreg.executor import Executor, single_threaded_blas
from mvreg.pairwise.aligners.base import register_aligner
from mvreg.pairwise.decision import rescore
from mvreg.pairwise.icp import coarse_icp, fine_icp
from mvreg.pairwise.preprocess import PreprocessedScan, scan_scales
from mvreg.pairwise.result import PairResult
from mvreg.pairwise.scoring import prepare_scans
from mvreg.scales import Scales


@register_aligner("icp-guess")
class IcpGuessAligner:
    """ICP from a guess, then the acceptance rule (module docstring)."""

    def __init__(
        self,
        align: AlignConfig | None = None,
        search: SearchConfig | None = None,
        *,
        scales: Scales | None = None,
        executor: Executor | int = 1,
    ):
        self.cfg = align or AlignConfig()
        self.scales = scales

    def prepare(self, pre: Sequence[PreprocessedScan]) -> None:
        """Build the shared caches."""
        prepare_scans(pre, self.scales)

    def align(
        self,
        pre_i: PreprocessedScan,
        pre_j: PreprocessedScan,
        guess: np.ndarray | None = None,
        seed: int = 0,
        *,
        i: int = 0,
        j: int = 1,
    ) -> PairResult:
        """ICP of scan j onto scan i from ``guess`` (T_i_j, (4, 4); None: identity)."""
        cfg = self.cfg
        start = time.perf_counter()
        scales = scan_scales(pre_i) if self.scales is None else self.scales
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
