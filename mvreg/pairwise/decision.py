"""The acceptance rule of a pair, the verification of a pose hypothesis, and its rank.

Takes scores from :func:`~mvreg.pairwise.scoring.score_alignment` and the
``AlignConfig``. Guarantees: the same rule decides every pair whatever proposed its pose
(feature RANSAC, ICP from a guess, rotation search):

``overlap_ratio >= min_overlap_ratio``, ``residual_ratio <= max_residual_ratio``,
``num_correspondences >= min_correspondences`` and, when defined (not NaN),
``free_space_violation <= max_free_space_violation``,
``unseen_violation <= max_unseen_violation`` and
``off_plane_matches >= PAIR_OFF_PLANE_MATCHES`` (:mod:`mvreg.pairwise.scoring`, scans that
surround their sensors: a pose whose close matches lie on one plane, a scene's ground,
leaves its heading about the normal and its slide open).

:func:`decide` returns "" when a pose passes, else the reason. :func:`verify` takes a
pose hypothesis through feature-level ICP, a loosened rule (``coarse_gate_slack``; a pair
failing it by a wide margin is rejected without fine ICP), fine ICP and the rule.
:func:`support` ranks accepted hypotheses of one pair (mutual correspondences, discounted
by the free-space share), :func:`choose` keeps the best. :func:`rescore` scores and
decides a :class:`~mvreg.pairwise.result.PairResult` again in place (after the scans'
noise estimates changed). Why the rule looks like this: ``docs/design/pairwise.md``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from mvreg.config.align import AlignConfig
from mvreg.executor import single_threaded_blas
from mvreg.pairwise.icp import coarse_icp, fine_icp
from mvreg.pairwise.preprocess import PreprocessedScan
from mvreg.pairwise.result import PairResult
from mvreg.pairwise.scoring import PAIR_OFF_PLANE_MATCHES, score_alignment
from mvreg.scales import Scales


def decide(scores: dict, cfg: AlignConfig, slack: float = 1.0) -> str:
    """'' when the scores pass the acceptance rule (thresholds loosened by ``slack``),
    else why not."""
    limit = cfg.max_residual_ratio * slack
    if not scores["residual_ratio"] <= limit:
        return f"residual {scores['residual_ratio']:.1f}x the scan noise (limit {limit:.1f})"
    if scores["overlap_ratio"] < cfg.min_overlap_ratio / slack:
        return f"overlap {scores['overlap_ratio']:.2f} below {cfg.min_overlap_ratio / slack:.2f}"
    if scores["num_correspondences"] < cfg.min_correspondences / slack:
        return f"only {scores['num_correspondences']} correspondences"
    limit = min(1.0, cfg.max_free_space_violation * slack)
    if scores["free_space_violation"] > limit:  # NaN (no view direction) passes
        return (
            f"{scores['free_space_violation']:.3f} of the points lie in the other scan's "
            f"free space (limit {limit:.3f})"
        )
    limit = min(1.0, cfg.max_unseen_violation * slack)
    if scores["unseen_violation"] > limit:  # NaN passes
        return (
            f"{scores['unseen_violation']:.3f} of the points lie where the other scan saw "
            f"nothing (limit {limit:.3f})"
        )
    off = scores.get("off_plane_matches", float("nan"))
    if off < PAIR_OFF_PLANE_MATCHES:  # NaN (feature level, or too few matches to judge) passes
        return (
            f"its close matches lie on one plane (only {off:.0f} off it): heading and slide "
            "along it are open"
        )
    return ""


def discount(share: float, limit: float) -> float:
    """1 - share / limit, at least 0; 1 when the share is undefined (NaN)."""
    return 1.0 if not np.isfinite(share) else max(0.0, 1.0 - share / limit)


def support(scores: dict, cfg: AlignConfig) -> float:
    """Rank of an accepted hypothesis: mutual correspondences, discounted by its share of
    points in the other view's free space (NaN: no discount)."""
    fs = scores["free_space_violation"]
    return scores["num_correspondences"] * discount(fs, cfg.max_free_space_violation)


def geometric_support(scores: dict, cfg: AlignConfig) -> float:
    """How well two scans' points support a pose: mutual correspondences, discounted by
    the share of points in the other view's free space and where it saw nothing (each
    relative to its limit; NaN: no discount); 0 when the pose fails the acceptance rule."""
    if decide(scores, cfg):
        return 0.0
    out = float(scores["num_correspondences"])
    for key, limit in (
        ("free_space_violation", cfg.max_free_space_violation),
        ("unseen_violation", cfg.max_unseen_violation),
    ):
        if limit > 0:
            out *= discount(scores[key], limit)
    return out


class Verified(NamedTuple):
    """A verified hypothesis: refined pose, reason ('' = accepted), fine scores (the
    feature-level ones when it failed there) and feature-level scores."""

    T: np.ndarray
    reason: str
    scores: dict
    coarse: dict


def verify(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    T: np.ndarray,
    cfg: AlignConfig,
    scales: Scales,
) -> Verified:
    """ICP from one hypothesis ``T`` (T_i_j) and the acceptance rule.

    Feature-level ICP and scores first; fine ICP and scores only when the loosened rule
    (``coarse_gate_slack``) passes there.
    """
    T = coarse_icp(pre_i, pre_j, T, cfg, scales.voxel)
    coarse = score_alignment(pre_i, pre_j, T, cfg, level="feature", scales=scales)
    reason = decide(coarse, cfg, slack=cfg.coarse_gate_slack)
    if reason:
        return Verified(T, reason, coarse, coarse)
    T = fine_icp(pre_i, pre_j, T, cfg.icp_fine_distance_voxels, cfg, scales.voxel)
    scores = score_alignment(pre_i, pre_j, T, cfg, scales=scales)
    return Verified(T, decide(scores, cfg), scores, coarse)


def screen(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    T: np.ndarray,
    cfg: AlignConfig,
    scales: Scales,
) -> bool:
    """Whether pose ``T`` passes the loosened rule on the feature level (no ICP)."""
    scores = score_alignment(pre_i, pre_j, T, cfg, level="feature", scales=scales)
    return not decide(scores, cfg, slack=cfg.coarse_gate_slack)


def choose(tried: Sequence[Verified], cfg: AlignConfig, stats: dict) -> Verified:
    """The accepted hypothesis with the most :func:`support` (the first tried when none
    is accepted); counts go to ``stats`` (hypotheses_tried, hypotheses_accepted)."""
    passed = [t for t in tried if not t.reason]
    stats["hypotheses_tried"] = len(tried)
    stats["hypotheses_accepted"] = len(passed)
    ranked = sorted(passed, key=lambda t: -support(t.scores, cfg))
    stats["accepted_hypotheses"] = [(t.T, t.scores) for t in ranked]
    return max(passed, key=lambda t: support(t.scores, cfg), default=tried[0])


def rescore(
    res: PairResult,
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    cfg: AlignConfig,
    *,
    scales: Scales | None = None,
) -> PairResult:
    """Score ``res.T_i_j`` again (e.g. after the scans' ``noise`` changed) and decide, in
    place, by the acceptance rule (:func:`decide`). Returns ``res``."""
    with single_threaded_blas():
        scores = score_alignment(pre_i, pre_j, res.T_i_j, cfg, scales=scales)
    res.overlap_ratio = scores["overlap_ratio"]
    res.inlier_rmse = scores["inlier_rmse"]
    res.num_correspondences = scores["num_correspondences"]
    res.fitness = scores["fitness"]
    res.residual_ratio = scores["residual_ratio"]
    res.free_space_violation = scores["free_space_violation"]
    res.unseen_violation = scores["unseen_violation"]
    res.stats["median_residual"] = scores["median_residual"]
    res.reason = decide(scores, cfg)
    res.accepted = not res.reason
    return res
