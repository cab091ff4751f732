"""The outcome of aligning one pair of scans.

Takes: what an aligner decided for scans i and j (pose, reason, scores). Returns a
:class:`PairResult`. Guarantees: ``T_i_j`` maps scan j's local points into scan i's
local frame; ``accepted`` is True exactly when ``reason`` is empty; a pair for which
nothing could be scored carries the scores of "no overlap at all" (fitness 0, overlap 0,
infinite residuals, NaN free-space tests), never made-up values.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mvreg.pairwise.preprocess import PreprocessedScan


@dataclass
class PairResult:
    """Outcome of aligning scan j to scan i.

    ``T_i_j`` (4, 4) maps scan j's points into scan i's frame. Scores as in
    :func:`mvreg.pairwise.scoring.score_alignment`; ``reason`` says why a pair was
    rejected ("" when accepted).
    """

    i: int
    j: int
    T_i_j: np.ndarray
    overlap_ratio: float
    inlier_rmse: float
    num_correspondences: int
    fitness: float
    accepted: bool
    reason: str
    residual_ratio: float = float("nan")
    free_space_violation: float = float("nan")
    unseen_violation: float = float("nan")
    seconds: float = 0.0
    names: tuple[str, str] = ("", "")
    stats: dict = field(default_factory=dict, repr=False)

    def __repr__(self) -> str:
        state = "accepted" if self.accepted else f"rejected: {self.reason}"
        return (
            f"PairResult({self.i}-{self.j}, overlap={self.overlap_ratio:.2f}, "
            f"residual_ratio={self.residual_ratio:.2f}, rmse={self.inlier_rmse:.3g}, "
            f"corr={self.num_correspondences}, fitness={self.fitness:.2f}, "
            f"free_space_violation={self.free_space_violation:.3f}, {state})"
        )


def no_overlap_scores() -> dict:
    """The scores of a pair for which no alignment was found to score."""
    return {
        "fitness": 0.0,
        "overlap_ratio": 0.0,
        "inlier_rmse": float("inf"),
        "residual_ratio": float("inf"),
        "num_correspondences": 0,
        "free_space_violation": float("nan"),
        "unseen_violation": float("nan"),
    }


def pair_result(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    i: int,
    j: int,
    T: np.ndarray,
    reason: str,
    scores: dict | None,
    stats: dict,
    start: float,
    *,
    fine_voxel: float,
) -> PairResult:
    """The PairResult of a decided pair.

    ``scores``: as from :func:`~mvreg.pairwise.scoring.score_alignment` (None: nothing was
    found to score); ``start``: ``time.perf_counter()`` when the pair was started;
    ``fine_voxel``: the run's fine voxel (``stats["median_residual_fine_voxels"]``).
    """
    if scores is None:
        scores = no_overlap_scores()
    median = scores.get("median_residual", float("inf"))
    stats["median_residual_fine_voxels"] = median / fine_voxel
    return PairResult(
        i=i,
        j=j,
        T_i_j=T,
        overlap_ratio=scores["overlap_ratio"],
        inlier_rmse=scores["inlier_rmse"],
        num_correspondences=scores["num_correspondences"],
        fitness=scores["fitness"],
        accepted=not reason,
        reason=reason,
        residual_ratio=scores["residual_ratio"],
        free_space_violation=scores["free_space_violation"],
        unseen_violation=scores["unseen_violation"],
        seconds=time.perf_counter() - start,
        names=(pre_i.name, pre_j.name),
        stats=stats,
    )


def pair_seed(seed: int, i: int, j: int) -> int:
    """Seed of pair (i, j): independent of the order in which pairs are run."""
    return int(np.random.SeedSequence([int(seed), int(i), int(j)]).generate_state(1)[0] >> 1)
