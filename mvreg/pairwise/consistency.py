"""Cycle consistency of the accepted pairs, before the global solve.

Each accepted pair (i, j) claims a relative pose ``T_i_j``. Around a cycle of pairs the
claimed poses must compose to the identity; a wrong pair (a flip of a near-symmetric
shape, a slide along a face) breaks every cycle it is part of, while a right pair closes
the cycles made of right pairs. The global solve with robust re-weighting is meant to sort
this out too, but it starts from the solution *with* the wrong pairs; on the teapot
(seed 2, 18 right and 3 wrong accepted pairs, 54 to 105 degrees off) the re-weighting
ended with the right pairs at weight 0 and every scan 2 to 26 degrees off.

Here every accepted pair is checked against the cycles of length 3 and 4 it closes with
other accepted pairs. A cycle's discrepancy is the median distance by which going round
it moves the points of the pair's scan j, in feature voxels; it is consistent below
``max_voxels``. Repeatedly, the pair with the most inconsistent cycles in excess of its
consistent ones is set aside and the counts are redone, until no pair is contradicted by
more cycles than confirm it (ties: the smaller overlap first). A pair with no cycles is
kept. Where cycles are few this can set aside a right pair instead of a wrong one (teapot,
seed 3: a right and a wrong pair shared exactly the same two inconsistent cycles and no
other); setting aside every tied pair was tried and lost more scans than it saved.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mvreg.geometry import invert_transform, transform_points
from mvreg.pairwise.align import PairResult
from mvreg.pairwise.preprocess import PreprocessedScan


def inconsistent_pairs(
    pre: Sequence[PreprocessedScan],
    results: Sequence[PairResult],
    max_voxels: float = 2.0,
    sample: int = 300,
) -> list[tuple[int, dict]]:
    """Indices into ``results`` of accepted pairs set aside (see the module docstring),
    in the order they were set aside, each with its counts of inconsistent and
    consistent cycles and the median discrepancy of its inconsistent ones (voxels)."""
    edges = {}
    for k, r in enumerate(results):
        if r.accepted:
            edges[(r.i, r.j)] = k
    if len(edges) < 3:
        return []
    v = pre[0].voxel_size
    pts = {}
    for p in {s for e in edges for s in e}:
        step = max(1, len(pre[p].points) // sample)
        pts[p] = pre[p].points[::step]

    def pose(a: int, b: int) -> np.ndarray:  # T_a_b from the pair's own pose
        if (a, b) in edges:
            return results[edges[(a, b)]].T_i_j
        return invert_transform(results[edges[(b, a)]].T_i_j)

    def discrepancy(i: int, j: int, path: list[int]) -> float:
        T = np.eye(4)
        for a, b in zip(path[:-1], path[1:], strict=True):
            T = T @ pose(a, b)
        q = pts[j]
        return (
            float(
                np.median(
                    np.linalg.norm(transform_points(T, q) - transform_points(pose(i, j), q), axis=1)
                )
            )
            / v
        )

    # Discrepancy of every cycle, computed once; a cycle is the set of its edges.
    active = set(edges)
    cycles: dict[frozenset, float] = {}
    neighbours: dict[int, set] = {}
    for a, b in edges:
        neighbours.setdefault(a, set()).add(b)
        neighbours.setdefault(b, set()).add(a)
    key = lambda a, b: (a, b) if (a, b) in edges else (b, a)  # noqa: E731
    for i, j in edges:
        for k in neighbours[i] & neighbours[j]:
            c = frozenset({key(i, j), key(j, k), key(i, k)})
            if c not in cycles:
                cycles[c] = discrepancy(i, j, [i, k, j])
        for k in neighbours[i] - {j}:
            for m in (neighbours[k] & neighbours[j]) - {i, k}:
                c = frozenset({key(i, j), key(i, k), key(k, m), key(m, j)})
                if c not in cycles:
                    cycles[c] = discrepancy(i, j, [i, k, m, j])

    removed = []
    while True:
        bad = dict.fromkeys(active, 0)
        good = dict.fromkeys(active, 0)
        worst: dict = {e: [] for e in active}
        for c, d in cycles.items():
            if not c <= active:
                continue
            for e in c:
                if d > max_voxels:
                    bad[e] += 1
                    worst[e].append(d)
                else:
                    good[e] += 1
        excess = {e: bad[e] - good[e] for e in active}
        e = max(active, key=lambda e: (excess[e], -results[edges[e]].overlap_ratio))
        if excess[e] <= 0:
            return removed
        active.discard(e)
        removed.append(
            (
                edges[e],
                {
                    "inconsistent_cycles": bad[e],
                    "consistent_cycles": good[e],
                    "median_discrepancy_voxels": float(np.median(worst[e])),
                },
            )
        )
