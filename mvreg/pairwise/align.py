"""Stage 3: align every candidate pair of scans with a registered aligner.

Takes the preprocessed scans of a run, the candidate pairs (i, j) and the ``align``
section; returns one :class:`~mvreg.pairwise.result.PairResult` per pair, in the order
of the pairs, each with ``T_i_j`` (scan j into scan i's frame), its scores and the
decision. Guarantees: the same results whatever the executor (each pair has its own
seed, :func:`~mvreg.pairwise.result.pair_seed`, and results come back in input order).

Each pair is decided by the acceptance rule alone (:mod:`mvreg.pairwise.decision`);
then :func:`reject_relative_outliers` compares pairs with each other: how large the
residual of a correct alignment is relative to the within-scan noise depends on the data
(synthetic i.i.d. noise, or real scans whose alignment residual is dominated by
calibration), so the reference is the median ``residual_ratio`` of the best-overlapping
quarter of the accepted pairs (at least 3), which are almost always right, and a pair
above ``relative_residual_factor`` times it is rejected as well, unless its median
residual is below ``relative_residual_floor_fine_voxels`` fine voxels (noise-free scans).
Measurements: ``docs/design/pairwise.md``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from mvreg.config.align import AlignConfig, SearchConfig
from mvreg.executor import Executor, make_executor, map_shared
from mvreg.pairwise.aligners import make_aligner
from mvreg.pairwise.preprocess import PreprocessedScan
from mvreg.pairwise.result import PairResult, pair_seed
from mvreg.scales import Scales


def align_pairs(
    pre: Sequence[PreprocessedScan],
    pairs: Sequence[tuple[int, int]],
    cfg: AlignConfig | None = None,
    seed: int = 0,
    progress: Callable[[PairResult], None] | None = None,
    executor: Executor | int = 2,
    *,
    scales: Scales | None = None,
    method: str = "feature-ransac",
    search: SearchConfig | None = None,
) -> list[PairResult]:
    """Align every candidate pair with the aligner ``method``; results in the order of
    ``pairs``, relative outliers rejected (module docstring).

    Pairs run on ``executor`` (an int: that many threads; KD-tree searches and NumPy
    release the GIL); each pair has its own seed (:func:`pair_seed`), so results do not
    depend on the executor. ``progress`` is called (from the calling thread) after each
    pair. The Open3D RANSAC backend always runs sequentially (reproducible only so).
    ``scales``: the run's (default: those each scan was preprocessed at).
    """
    cfg = cfg or AlignConfig()
    aligner = make_aligner(method, cfg, search, scales=scales, executor=1)
    aligner.prepare(pre)  # run-wide state and shared caches, before the threads start
    # Open3D's RANSAC is reproducible on one thread only.
    executor = make_executor(1 if cfg.ransac_backend == "open3d" else executor)
    labels = [f"pair {pre[i].name}, {pre[j].name}" for i, j in pairs]
    shared = (aligner, list(pre), seed)  # sent to each worker once (map_shared)
    results = map_shared(executor, align_task, shared, pairs, progress, labels)
    reject_relative_outliers(results, cfg)
    return results


def align_task(shared: tuple, pair: tuple[int, int]) -> PairResult:
    """One pair as a task: ``shared`` is (aligner, preprocessed scans, run seed); the
    pair's seed comes from the run seed and the pair (:func:`pair_seed`)."""
    aligner, pre, seed = shared
    i, j = pair
    return aligner.align(pre[i], pre[j], None, pair_seed(seed, i, j), i=i, j=j)


def reject_relative_outliers(results: Sequence[PairResult], cfg: AlignConfig | None = None):
    """Reject accepted pairs whose residual_ratio is far above that of the best pairs.

    Reference: median residual_ratio of the best-overlapping quarter (at least 3) of the
    accepted pairs. Pairs above ``cfg.relative_residual_factor`` times it are marked
    rejected, in place. Returns the reference (None when there are fewer than 3 pairs).
    """
    cfg = cfg or AlignConfig()
    accepted = [r for r in results if r.accepted]
    if cfg.relative_residual_factor is None or len(accepted) < 3:
        return None
    accepted.sort(key=lambda r: -r.overlap_ratio)
    best = accepted[: max(3, len(accepted) // 4)]
    reference = float(np.median([r.residual_ratio for r in best]))
    limit = cfg.relative_residual_factor * reference
    floor = cfg.relative_residual_floor_fine_voxels
    for r in results:
        r.stats["residual_reference"] = reference
        tiny = r.stats.get("median_residual_fine_voxels", float("inf")) <= floor
        if r.accepted and r.residual_ratio > limit and not tiny:
            r.accepted = False
            r.reason = (
                f"residual {r.residual_ratio:.2f}x the scan noise, above "
                f"{cfg.relative_residual_factor:g}x that of the best-overlapping pairs "
                f"({reference:.2f})"
            )
    return reference
