"""``feature-ransac``: align two scans from FPFH feature matches, no initial pose needed.

Per pair (i, j), mapping scan j into scan i's frame (``T_i_j``):

1. feature matches (:mod:`mvreg.pairwise.features`) in a descriptor basis fitted on all
   scans of the run (:meth:`FeatureRansacAligner.prepare`) or on the pair alone;
2. RANSAC (:mod:`mvreg.pairwise.hypotheses`, backend ``ransac_backend``): up to
   ``ransac_hypotheses_tried`` distinct hypotheses, best first;
3. verification (:func:`mvreg.pairwise.decision.verify`): the first hypothesis fully
   (ICP on both levels and the acceptance rule); each other one is screened first by
   ``screen_icp_iterations`` feature-level ICP iterations and the loosened rule, and
   verified fully only when it passes and ends somewhere new (not within a feature voxel
   of a pose already tried). On near-symmetric shapes the first-ranked hypothesis is
   often a flip or a turn about an axis, and the right one lies further down;
4. among the accepted hypotheses the best supported one is kept
   (:func:`~mvreg.pairwise.decision.choose`); when none is accepted, the first one's
   result (rejected, with its reason).

Deterministic for a given seed (the Open3D backend only on one thread). ``guess`` is
not used. Stats: ``feature_matches``, ``hypotheses_drawn``, ``candidate_fitness``,
``hypotheses_tried``, ``hypotheses_accepted``, ``coarse`` (feature-level scores),
``seconds_ransac``, ``seconds_icp``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

from mvreg.config.align import AlignConfig
from mvreg.executor import single_threaded_blas
from mvreg.pairwise.aligners.base import BaseAligner, register_aligner
from mvreg.pairwise.decision import Verified, choose, screen, verify
from mvreg.pairwise.features import FeatureBasis, reduced_tree
from mvreg.pairwise.hypotheses import RANSAC_BACKENDS, same_pose, scan_extent
from mvreg.pairwise.icp import coarse_icp
from mvreg.pairwise.preprocess import PreprocessedScan
from mvreg.pairwise.result import PairResult, pair_result
from mvreg.scales import Scales


@register_aligner("feature-ransac")
class FeatureRansacAligner(BaseAligner):
    """Feature RANSAC, then ICP and the acceptance rule (module docstring).

    ``feature_basis``: the descriptor PCA shared by a run (set by :meth:`prepare`; None:
    fitted on each pair alone).
    """

    def __init__(self, align=None, search=None, *, scales=None, executor=1, feature_basis=None):
        super().__init__(align, search, scales=scales, executor=executor)
        self.feature_basis: FeatureBasis | None = feature_basis

    def prepare(self, pre: Sequence[PreprocessedScan]) -> None:
        """Fit the descriptor basis on all scans; build the shared caches."""
        self.feature_basis = FeatureBasis.fit([p.features for p in pre], self.cfg.feature_dims)
        super().prepare(pre)
        for p in pre:
            reduced_tree(p, self.feature_basis)

    def align(self, pre_i, pre_j, guess=None, seed=0, *, i=0, j=1) -> PairResult:
        """Align scan j to scan i (``guess`` unused); deterministic for ``seed``."""
        start = time.perf_counter()
        scales = self.scales_for(pre_i)
        with single_threaded_blas():
            return self._align(pre_i, pre_j, seed, i, j, scales, start)

    def _align(self, pre_i, pre_j, seed, i, j, scales: Scales, start: float) -> PairResult:
        cfg = self.cfg
        ransac = RANSAC_BACKENDS[cfg.ransac_backend]
        T, stats = ransac(pre_i, pre_j, cfg, seed, self.feature_basis, scales.voxel)
        stats["seconds_ransac"] = time.perf_counter() - start
        candidates = stats.pop("candidates", [T])[: cfg.ransac_hypotheses_tried]
        # Kept for later stages (placing a scan on the model of verified ones): a pair too
        # small to accept may still hold the right pose among its hypotheses.
        stats["pose_hypotheses"] = list(candidates)
        reason, scores = "", None
        if not stats["ok"]:
            reason = "feature matching found no consistent alignment"
        else:
            tried = self._verify_distinct(pre_i, pre_j, candidates, scales)
            T, reason, scores, stats["coarse"] = choose(tried, cfg, stats)
        stats["seconds_icp"] = time.perf_counter() - start - stats["seconds_ransac"]
        return pair_result(
            pre_i, pre_j, i, j, T, reason, scores, stats, start, fine_voxel=scales.fine_voxel
        )

    def _verify_distinct(self, pre_i, pre_j, candidates, scales: Scales) -> list[Verified]:
        """The first hypothesis verified; each other one screened, and verified when it
        passes and leads somewhere new (module docstring, step 3)."""
        cfg, v = self.cfg, scales.voxel
        tried = [verify(pre_i, pre_j, candidates[0], cfg, scales)]
        centre, radius = scan_extent(pre_j.points)
        seen = [tried[0].T]
        for T0 in candidates[1:]:
            T0 = coarse_icp(pre_i, pre_j, T0, cfg, v, cfg.screen_icp_iterations)
            if any(same_pose(T0, K, v, centre, radius) for K in seen):
                continue
            seen.append(T0)
            if screen(pre_i, pre_j, T0, cfg, scales):
                tried.append(verify(pre_i, pre_j, T0, cfg, scales))
                seen.append(tried[-1].T)
        return tried


def align_pair(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    cfg: AlignConfig | None = None,
    seed: int = 0,
    *,
    i: int = 0,
    j: int = 1,
    feature_basis: FeatureBasis | None = None,
    scales: Scales | None = None,
) -> PairResult:
    """Align scan j to scan i with ``feature-ransac`` and score the result.

    Deterministic for a given ``seed``. ``i`` and ``j`` only label the result.
    ``feature_basis``: PCA of the descriptors shared by a run (fitted on the pair if None).
    ``scales``: the run's (default: those ``pre_i`` was preprocessed at).
    """
    aligner = FeatureRansacAligner(cfg, scales=scales, feature_basis=feature_basis)
    return aligner.align(pre_i, pre_j, None, seed, i=i, j=j)
