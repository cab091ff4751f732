"""Stage 3b: connect the scans that pairwise alignment left outside the largest set.

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
