"""Loop closures: scans whose chained poses come back near earlier ones, each verified by
ICP from the chained guess (then feature RANSAC), and must overlap enough.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mvreg.config import RegisterConfig
from mvreg.config.sequence import SequenceConfig
from mvreg.io.loaders import Scan
from mvreg.pairwise.preprocess import PreprocessedScan
from mvreg.pairwise.result import PairResult
from mvreg.pipeline.run import NoProgress
from mvreg.sequence.pairs import align_with_guesses, loop_gate, ransac_fallback, relative_pose


@dataclass
class LoopClosures:
    """Loop-closure candidates and their verification.

    radius: the search radius at zero path (data units); candidates: (i, j) pairs tried;
    results: one PairResult per candidate (``stats["kind"] == "loop"``).
    """

    radius: float
    candidates: list[tuple[int, int]]
    results: list[PairResult]


def loop_closures(
    pre: Sequence[PreprocessedScan],
    scans: Sequence[Scan],
    T_chain: np.ndarray,
    done: Sequence[PairResult],
    cfg: RegisterConfig,
    seq: SequenceConfig,
    progress=None,
) -> LoopClosures:
    """Candidates from the chained poses (:func:`loop_candidates`, pairs in ``done``
    left out), each verified by ICP from the chained guess, then feature RANSAC; a loop
    pair must also overlap by ``seq.loop_min_overlap_ratio``.

    Args:
        T_chain: (M, 4, 4) poses chained from the verified consecutive pairs.
    """
    prog = progress if progress is not None else NoProgress()
    ranges = [float(np.median(np.linalg.norm(s.points, axis=1))) for s in scans]
    radius = seq.loop_radius_ranges * float(np.median(ranges))
    tried = {(r.i, r.j) for r in done}
    pairs = [p for p in loop_candidates(T_chain, radius, seq) if p not in tried]
    prog.stage("loop closures", len(pairs))
    results = align_with_guesses(
        pre, pairs, [[("chain", relative_pose(T_chain, i, j))] for i, j in pairs], cfg,
        kind="loop", advance=prog.advance,
    )  # fmt: skip
    for r in results:
        loop_gate(r, seq)
    prog.stage("loop closures: feature RANSAC", sum(not r.accepted for r in results))
    results = ransac_fallback(pre, results, cfg, seq, advance=prog.advance)
    return LoopClosures(radius, pairs, results)


def loop_candidates(
    T_odom_scan: np.ndarray, radius: float, seq: SequenceConfig | None = None
) -> list[tuple[int, int]]:
    """Pairs (i, j), i < j, whose odometry positions came back close (module docstring).

    Args:
        T_odom_scan: (M, 4, 4) poses in one frame.
        radius: search radius at zero path (data units).
    Returns:
        at most ``loop_max_per_scan`` pairs per later scan j (its nearest), sorted.
    """
    seq = seq or SequenceConfig()
    pos = T_odom_scan[:, :3, 3]
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    out = []
    for j in range(len(pos)):
        i = np.arange(0, j - seq.loop_min_frames + 1)
        if len(i) == 0 or seq.loop_max_per_scan == 0:
            continue
        travelled = path[j] - path[i]
        dist = np.linalg.norm(pos[i] - pos[j], axis=1)
        ok = (travelled >= seq.loop_min_path_radii * radius) & (
            dist <= radius + seq.loop_drift_fraction * travelled
        )
        best = i[ok][np.argsort(dist[ok], kind="stable")[: seq.loop_max_per_scan]]
        out.extend((int(a), j) for a in best)
    return sorted(out)
