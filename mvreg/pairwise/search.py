"""Stage 3b: search again for the scans that feature matching placed badly or not at all.

:func:`confirm_weak_scans`: a scan none of whose accepted pairs is confirmed by a cycle
(:func:`~mvreg.pairwise.consistency.confirmed_scans`) has its rejected candidate pairs
searched with the aligner ``method`` (nearest scans by global descriptor first) until a
cycle confirms it or they run out. Sparse scans of machined parts are where this pays:
feature RANSAC proposes flips of their near-symmetric faces, which the free-space tests
rightly reject, and the right pose is never proposed (``docs/design/pairwise.md``).
The pipeline calls it after a first verified pass, for the scans that pass did not verify
(:meth:`mvreg.pipeline.stages.UnorderedMode.recover`), so data that feature matching
handles never pays for it.

:func:`connect_unconnected`:

Takes the preprocessed scans, the pair results so far, the ``align`` and ``search``
sections; returns the results with searched pairs added or substituted. For each scan
outside the largest connected set of accepted pairs (in index order), its
``search.partners`` most similar scans inside the set (pooled FPFH,
:func:`~mvreg.pairwise.candidates.global_descriptor`) are tried with the aligner
``method`` (default ``rotation-search``, :mod:`mvreg.pairwise.aligners.rotation_search`,
which needs no feature matches). The first partner that yields an accepted pose
connects the scan; the search then moves on to the next unconnected scan, against the
grown set. Runs only when some scan is unconnected, so data that feature matching
handles never pays for it. Deterministic: the partners are ordered by descriptor
distance, ties by index. Costs and the cases it was made for: ``docs/design/pairwise.md``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from mvreg.config.align import AlignConfig, SearchConfig
from mvreg.executor import Executor
from mvreg.pairwise.aligners import PairwiseAligner, make_aligner
from mvreg.pairwise.candidates import global_descriptor
from mvreg.pairwise.consistency import confirmed_scans
from mvreg.pairwise.preprocess import PreprocessedScan
from mvreg.pairwise.result import PairResult
from mvreg.scales import Scales


def components(m: int, results: Sequence[PairResult]) -> np.ndarray:
    """(m,) label of each scan's connected set under the accepted pairs."""
    parent = list(range(m))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for r in results:
        if r.accepted:
            parent[find(r.i)] = find(r.j)
    return np.array([find(a) for a in range(m)])


def connect_unconnected(
    pre: Sequence[PreprocessedScan],
    results: list[PairResult],
    cfg: AlignConfig | None = None,
    search: SearchConfig | None = None,
    progress: Callable[[PairResult], None] | None = None,
    executor: Executor | int = 2,
    *,
    scales: Scales | None = None,
    method: str = "rotation-search",
) -> list[PairResult]:
    """``results`` with searched pairs for scans outside the largest connected set.

    A searched pair replaces the failed result of the same pair (or is appended when the
    pair was not a candidate). Scans are visited in index order; each tries its
    ``search.partners`` nearest scans of the (growing) largest set by global descriptor.
    The aligner runs its own work on ``executor``; ``progress`` is called after each
    searched pair. ``scales``: the run's (default: those each scan was preprocessed at).
    """
    cfg, search = cfg or AlignConfig(), search or SearchConfig()
    results = list(results)
    m = len(pre)
    if not search.enabled or m < 2:
        return results
    desc = np.stack([global_descriptor(p) for p in pre])
    index = {(r.i, r.j): k for k, r in enumerate(results)}
    aligner: PairwiseAligner | None = None
    for a in range(m):
        label = components(m, results)
        sizes = np.bincount(label, minlength=m)
        main = int(np.argmax(sizes))
        if label[a] == main:
            continue
        if aligner is None:
            aligner = make_aligner(method, cfg, search, scales=scales, executor=executor)
            aligner.prepare(pre)
        inside = np.flatnonzero(label == main)
        order = inside[np.argsort(np.linalg.norm(desc[inside] - desc[a], axis=1), kind="stable")]
        for b in order[: search.partners]:
            i, j = (int(min(a, b)), int(max(a, b)))
            res = aligner.align(pre[i], pre[j], i=i, j=j)
            if (i, j) in index:
                if res.accepted or not results[index[(i, j)]].accepted:
                    results[index[(i, j)]] = res
            else:
                index[(i, j)] = len(results)
                results.append(res)
            if progress is not None:
                progress(res)
            if res.accepted:
                break
    return results


def confirm_weak_scans(
    pre: Sequence[PreprocessedScan],
    results: list[PairResult],
    cfg: AlignConfig | None = None,
    search: SearchConfig | None = None,
    executor: Executor | int = 2,
    *,
    max_voxels: float = 2.0,
    scales: Scales | None = None,
    method: str = "rotation-search",
    only: Sequence[int] | None = None,
) -> list[PairResult]:
    """``results`` with rejected pairs of unconfirmed scans searched again (module
    docstring); a searched pair replaces the rejected result when it is accepted.

    Scans are visited in index order (only those of ``only`` when given); ``max_voxels``
    is the cycle check's limit. Deterministic: the aligner is, and the order is fixed."""
    cfg, search = cfg or AlignConfig(), search or SearchConfig()
    results = list(results)
    if not search.enabled or not search.weak_scans or len(pre) < 3:
        return results
    confirmed = confirmed_scans(pre, results, max_voxels, scales=scales)
    desc = np.stack([global_descriptor(p) for p in pre])
    aligner: PairwiseAligner | None = None
    for a in range(len(pre)) if only is None else sorted(only):
        if a in confirmed:
            continue
        tried = [k for k, r in enumerate(results) if a in (r.i, r.j) and not r.accepted]
        other = [results[k].j if results[k].i == a else results[k].i for k in tried]
        for n in np.argsort(np.linalg.norm(desc[other] - desc[a], axis=1), kind="stable"):
            k = tried[n]
            if method == "rotation-search" and results[k].stats.get("search"):
                continue  # already this search's result (connect_unconnected): the same again
            if aligner is None:
                aligner = make_aligner(method, cfg, search, scales=scales, executor=executor)
                aligner.prepare(pre)
            r = results[k]
            res = aligner.align(pre[r.i], pre[r.j], i=r.i, j=r.j)
            if not res.accepted:
                continue
            results[k] = res
            confirmed = confirmed_scans(pre, results, max_voxels, scales=scales)
            if a in confirmed:
                break
    return results
