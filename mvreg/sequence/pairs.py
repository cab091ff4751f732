"""Sequential pairs of a sequence: (k, k+1) and skip pairs by ICP from the odometry and
from a constant-velocity guess, a feature RANSAC fallback, and the chained poses.

Scores and the acceptance rule are those of ``register`` except the residual scale
(:func:`calibrate_noise`). Of several alignments of one pair the one bringing more of the
scans into contact (fitness) is kept.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from mvreg.config import RegisterConfig
from mvreg.config.sequence import SequenceConfig
from mvreg.executor import ThreadExecutor
from mvreg.geometry import invert_transform, transform_points
from mvreg.pairwise import PairResult, align_pair, make_aligner, pair_seed, rescore
from mvreg.pairwise.preprocess import PreprocessedScan
from mvreg.pipeline.run import NoProgress
from mvreg.sequence.odometry import Odometry, scale_motion
from mvreg.sequence.preprocess import ensure_features


def sequential_pairs(num_scans: int, skip_pairs: int = 1) -> list[tuple[int, int]]:
    """(k, k+1), ..., (k, k+1+skip_pairs) for every k, in order of k."""
    return [
        (k, k + s) for k in range(num_scans) for s in range(1, skip_pairs + 2) if k + s < num_scans
    ]


def calibrate_noise(pre: Sequence[PreprocessedScan], results: Sequence[PairResult]) -> float | None:
    """Set every scan's ``noise`` to the residual that correct consecutive alignments leave.

    The within-scan estimate of :func:`~mvreg.pairwise.preprocess.preprocess` means
    nothing for a LiDAR scan: the nearest neighbours of a point lie along its ring, on
    a line, and the fitted tangent plane contains that line, so the estimate is near 0;
    and what a correct alignment of two such scans leaves is set by how differently
    their rings sample the scene, not by the range noise. So the reference is measured
    on the (k, k+1) pairs after ICP from the odometry: the lower quartile of their median
    residuals (robust while up to three quarters of them are wrong). Returns it, or None
    (``noise`` left as it was) when no consecutive pair has any point in contact.
    """
    med = [
        r.stats["median_residual"]
        for r in results
        if r.j == r.i + 1 and np.isfinite(r.stats.get("median_residual", np.inf))
    ]
    if not med:
        return None
    reference = max(float(np.percentile(med, 25)), 1e-12 * pre[0].voxel_size)
    for p in pre:
        p.noise = reference
    return reference


def _guess_distance(pre_j: PreprocessedScan, T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Median displacement of scan j's feature-level points between two guesses."""
    return float(
        np.median(
            np.linalg.norm(
                transform_points(T_a, pre_j.points) - transform_points(T_b, pre_j.points), axis=1
            )
        )
    )


def _better(a: PairResult, b: PairResult) -> PairResult:
    """Of two alignments of the same pair: the accepted one, else the larger fitness
    (the share of scan j brought into contact with scan i)."""
    return a if (a.accepted, a.fitness) >= (b.accepted, b.fitness) else b


def align_with_guesses(
    pre: Sequence[PreprocessedScan],
    pairs: Sequence[tuple[int, int]],
    guesses: Sequence[Sequence[tuple[str, np.ndarray]]],
    cfg: RegisterConfig,
    *,
    kind: str,
    advance: Callable[[], None] | None = None,
) -> list[PairResult]:
    """ICP of each pair (i, j) from each of its guesses ``(label, T_i_j)`` (skipping a
    guess within half a voxel of one already tried), keeping the better result
    (:func:`_better`). Runs on ``cfg.threads`` threads; results in the order
    of ``pairs`` with ``stats["kind"] = kind`` and ``stats["init"]`` = the guess's label.
    """
    icp_guess = make_aligner("icp-guess", cfg.align, cfg.search)
    icp_guess.prepare(pre)  # shared trees, built before the threads start

    def run(n: int) -> PairResult:
        i, j = pairs[n]
        best, tried = None, []
        for label, guess in guesses[n]:
            if any(_guess_distance(pre[j], guess, t) < 0.5 * pre[j].voxel_size for t in tried):
                continue
            tried.append(guess)
            res = icp_guess.align(pre[i], pre[j], guess, i=i, j=j)
            res.stats |= {"kind": kind, "init": label}
            best = res if best is None else _better(best, res)
        best.stats["guesses_tried"] = len(tried)
        return best

    return threads_map(run, list(range(len(pairs))), cfg.threads, advance)


def relative_pose(T_scan: np.ndarray, i: int, j: int) -> np.ndarray:
    return invert_transform(T_scan[i]) @ T_scan[j]


def sequential_results(
    pre: Sequence[PreprocessedScan],
    odom: Odometry,
    times: np.ndarray,
    cfg: RegisterConfig,
    seq: SequenceConfig,
    progress=None,
) -> tuple[list[PairResult], float | None]:
    """Consecutive pairs, then the skip pairs (see the module docstring).

    1. (k, k+1) by ICP from the odometry; the residual scale is calibrated on them
       (:func:`calibrate_noise`) and they are re-scored.
    2. (k, k+1) again from a constant-velocity guess (the verified step (k-1, k), scaled
       by the ratio of time steps) where it differs from the odometry's: when the
       odometry lost track (it predicts from its own, possibly wrong, velocity), this
       guess still lies in ICP's basin.
    3. Skip pairs (k, k+2 ..) from the odometry and from the chain of verified steps.
    4. Feature RANSAC for every pair still rejected (``fallback_ransac``).

    Returns the results (consecutive pairs first) and the calibrated residual scale.
    """
    prog = progress if progress is not None else NoProgress()
    m = len(pre)
    T_odo = odom.T_odom_scan
    steps = [(k, k + 1) for k in range(m - 1)]
    prog.stage("consecutive pairs", len(steps))
    results = align_with_guesses(
        pre, steps, [[("odometry", relative_pose(T_odo, i, j))] for i, j in steps], cfg,
        kind="sequential", advance=prog.advance,
    )  # fmt: skip
    noise = calibrate_noise(pre, results)
    for r in results:
        rescore(r, pre[r.i], pre[r.j], cfg.align)
    dt = np.diff(times)
    redo, guesses = [], []
    for k in range(1, m - 1):
        prev = results[k - 1]
        if prev.accepted:
            cv = scale_motion(prev.T_i_j, dt[k] / dt[k - 1])
            if (
                _guess_distance(pre[k + 1], cv, relative_pose(T_odo, k, k + 1))
                >= 0.5 * pre[k].voxel_size
            ):
                redo.append(k)
                guesses.append([("constant velocity", cv)])
    prog.stage("consecutive pairs: constant velocity", len(redo))
    again = align_with_guesses(
        pre, [steps[k] for k in redo], guesses, cfg, kind="sequential", advance=prog.advance
    )
    for k, res in zip(redo, again, strict=True):
        results[k] = _better(results[k], res)
    T_chain = chain_poses(T_odo, results)
    skips = [(i, j) for i, j in sequential_pairs(m, seq.skip_pairs) if j > i + 1]
    prog.stage("skip pairs", len(skips))
    skip_guesses = [
        [("odometry", relative_pose(T_odo, i, j)), ("chain", relative_pose(T_chain, i, j))]
        for i, j in skips
    ]
    results += align_with_guesses(
        pre, skips, skip_guesses, cfg, kind="sequential", advance=prog.advance
    )
    prog.stage("sequential pairs: feature RANSAC", sum(not r.accepted for r in results))
    return ransac_fallback(pre, results, cfg, seq, advance=prog.advance), noise


def ransac_fallback(
    pre: Sequence[PreprocessedScan],
    results: list[PairResult],
    cfg: RegisterConfig,
    seq: SequenceConfig,
    advance: Callable[[], None] | None = None,
) -> list[PairResult]:
    """Retry every rejected pair with feature RANSAC + ICP (:func:`~mvreg.pairwise.align_pair`),
    which needs no initial guess; a retry replaces the pair when it is accepted (for
    loop pairs, also with ``seq.loop_min_overlap_ratio``). Returns the new list."""
    todo = [k for k, r in enumerate(results) if not r.accepted]
    if not todo or not seq.fallback_ransac:
        return results
    for k in todo:
        ensure_features(pre[results[k].i], cfg.preprocess)
        ensure_features(pre[results[k].j], cfg.preprocess)

    def run(k: int) -> PairResult:
        old = results[k]
        alt = align_pair(
            pre[old.i], pre[old.j], cfg.align, pair_seed(cfg.seed, old.i, old.j), i=old.i, j=old.j
        )
        alt.stats |= {"init": "feature RANSAC", "kind": old.stats.get("kind", "")}
        alt.stats["odometry_attempt"] = old.reason
        loop_gate(alt, seq)
        return alt if alt.accepted else old

    out = list(results)
    for k, res in zip(todo, threads_map(run, todo, cfg.threads, advance), strict=True):
        out[k] = res
    return out


def loop_gate(res: PairResult, seq: SequenceConfig) -> None:
    if (
        res.stats.get("kind") == "loop"
        and res.accepted
        and res.overlap_ratio < seq.loop_min_overlap_ratio
    ):
        res.accepted = False
        res.reason = (
            f"loop closure overlap {res.overlap_ratio:.2f} below {seq.loop_min_overlap_ratio:.2f}"
        )


def chain_poses(T_odom_scan: np.ndarray, results: Sequence[PairResult]) -> np.ndarray:
    """(M, 4, 4) poses chained along the sequence, for finding loop-closure candidates.

    Scan k is placed from the nearest earlier scan i that an accepted sequential pair
    (i, k) links it to (i = k-1 when that pair was accepted; a skip pair bridges a scan
    that failed), else by the odometry's step from scan k-1.
    """
    into: dict[int, PairResult] = {}
    for r in results:
        if r.accepted and r.stats.get("kind") == "sequential" and r.i < r.j:
            if r.j not in into or r.i > into[r.j].i:
                into[r.j] = r
    out = np.empty_like(T_odom_scan)
    out[0] = np.eye(4)
    for k in range(1, len(T_odom_scan)):
        r = into.get(k)
        if r is not None:
            out[k] = out[r.i] @ r.T_i_j
        else:
            out[k] = out[k - 1] @ relative_pose(T_odom_scan, k - 1, k)
    return out


def threads_map(fn, items, workers: int, advance: Callable[[], None] | None = None) -> list:
    """``fn`` over ``items`` on ``workers`` threads, results in order; ``advance()`` after each."""
    progress = None if advance is None else (lambda _r: advance())
    return ThreadExecutor(workers).map(fn, items, progress)
