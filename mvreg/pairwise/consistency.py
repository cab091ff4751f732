"""Cycle consistency of the accepted pairs, before the global solve.

Takes the preprocessed scans, the pair results and a threshold ``max_voxels`` (in
feature voxels); returns the accepted pairs to set aside (indices into the results, in
the order they were set aside, with the evidence). Deterministic. A pair with no cycles
is never set aside, and a pair is set aside only while it is contradicted by more
cycles than confirm it.

Each accepted pair (i, j) claims a relative pose ``T_i_j``. Around a cycle of pairs the
claimed poses must compose to the identity; a wrong pair (a flip of a near-symmetric
shape, a slide along a face) breaks every cycle it is part of, while a right pair closes
the cycles made of right pairs. Every accepted pair is checked against the cycles of
length 3 and 4 it closes with other accepted pairs. A cycle's discrepancy is the median
distance by which going round it moves the points of the pair's scan j, in feature
voxels; it is consistent below ``max_voxels``. Repeatedly, the pair with the most
inconsistent cycles in excess of its consistent ones is set aside and the counts are
redone, until no pair is contradicted by more cycles than confirm it.

Counting alone cannot tell the wrong pair of a cycle from the right ones when cycles are
few, so with the scans' geometry at hand (``align_cfg``) each contradicted pair is also
tested against the poses its inconsistent cycles imply for it: a pair whose own pose is
worse supported by the two scans' points than some cycle's pose
(:func:`~mvreg.pairwise.decision.geometric_support`), or not supported at all, is wrong
on the evidence of both the cycle and the data, and the one with the largest margin is
set aside first. Only when no contradicted pair is beaten that way does the count decide
(ties: the smaller overlap first). Why: ``docs/design/pairwise.md``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mvreg.config.align import AlignConfig
from mvreg.geometry import invert_transform, transform_points
from mvreg.pairwise.decision import geometric_support
from mvreg.pairwise.preprocess import PreprocessedScan
from mvreg.pairwise.result import PairResult
from mvreg.pairwise.scoring import score_alignment
from mvreg.scales import Scales


def inconsistent_pairs(
    pre: Sequence[PreprocessedScan],
    results: Sequence[PairResult],
    max_voxels: float = 2.0,
    sample: int = 300,
    align_cfg: AlignConfig | None = None,
    max_cycles_tested: int = 6,
    *,
    scales: Scales | None = None,
) -> list[tuple[int, dict]]:
    """Indices into ``results`` of accepted pairs set aside (see the module docstring),
    in the order they were set aside, each with its counts of inconsistent and
    consistent cycles, the median discrepancy of its inconsistent ones (voxels) and,
    when ``align_cfg`` is given, the geometric support of its own pose and of the best
    of (up to ``max_cycles_tested`` of) its inconsistent cycles' poses.

    ``scales``: the run's (default: the voxel ``pre[0]`` was preprocessed at)."""
    edges = {}
    for k, r in enumerate(results):
        if r.accepted:
            edges[(r.i, r.j)] = k
    if len(edges) < 3:
        return []
    voxel = pre[0].voxel_size if scales is None else scales.voxel
    check = _Cycles(pre, results, edges, sample, voxel, align_cfg, scales, max_cycles_tested)
    active = set(edges)
    removed = []
    while True:
        bad, good, worst, bad_cycles = check.count(active, max_voxels)
        excess = {e: bad[e] - good[e] for e in active}
        contradicted = sorted(e for e in active if excess[e] > 0)
        if not contradicted:
            return removed
        e, info = check.beaten_most(contradicted, bad_cycles)
        if e is None:
            e = max(contradicted, key=lambda e: (excess[e], -results[edges[e]].overlap_ratio))
        active.discard(e)
        removed.append(
            (
                edges[e],
                {
                    "inconsistent_cycles": bad[e],
                    "consistent_cycles": good[e],
                    "median_discrepancy_voxels": float(np.median(worst[e])),
                    **info,
                },
            )
        )


def confirmed_scans(
    pre: Sequence[PreprocessedScan],
    results: Sequence[PairResult],
    max_voxels: float = 2.0,
    sample: int = 300,
    *,
    scales: Scales | None = None,
) -> set[int]:
    """Scans with an accepted pair that closes more consistent cycles (length 3 or 4,
    discrepancy within ``max_voxels`` feature voxels) than inconsistent ones, and at least
    one: the scans whose pose some cycle of pairs confirms. Counting only (no geometry)."""
    edges = {(r.i, r.j): k for k, r in enumerate(results) if r.accepted}
    if len(edges) < 3:
        return set()
    voxel = pre[0].voxel_size if scales is None else scales.voxel
    check = _Cycles(pre, results, edges, sample, voxel, None, scales, 0)
    bad, good, _, _ = check.count(set(edges), max_voxels)
    return {s for e in edges if good[e] > bad[e] for s in e}


class _Cycles:
    """The cycles of length 3 and 4 of the accepted pairs, their discrepancies (computed
    once; a cycle is the set of its edges) and the support of the poses they imply."""

    def __init__(self, pre, results, edges, sample, voxel, align_cfg, scales, max_tested):
        self.pre, self.results, self.edges, self.voxel = pre, results, edges, voxel
        self.align_cfg, self.scales, self.max_tested = align_cfg, scales, max_tested
        self.pts = {}
        for p in {s for e in edges for s in e}:
            step = max(1, len(pre[p].points) // sample)
            self.pts[p] = pre[p].points[::step]
        self.cycles: dict[frozenset, float] = {}
        self.loops: dict[frozenset, list[int]] = {}  # each cycle's scans in order round it
        self.support_cache: dict = {}
        self._find_cycles()

    def pose(self, a: int, b: int) -> np.ndarray:  # T_a_b from the pair's own pose
        if (a, b) in self.edges:
            return self.results[self.edges[(a, b)]].T_i_j
        return invert_transform(self.results[self.edges[(b, a)]].T_i_j)

    def compose(self, path: Sequence[int]) -> np.ndarray:  # T_first_last along the path
        T = np.eye(4)
        for a, b in zip(path[:-1], path[1:], strict=True):
            T = T @ self.pose(a, b)
        return T

    def discrepancy(self, i: int, j: int, path: list[int]) -> float:
        T = self.compose(path)
        q = self.pts[j]
        moved = transform_points(T, q) - transform_points(self.pose(i, j), q)
        return float(np.median(np.linalg.norm(moved, axis=1))) / self.voxel

    def _find_cycles(self) -> None:
        edges, cycles, loops = self.edges, self.cycles, self.loops
        neighbours: dict[int, set] = {}
        for a, b in edges:
            neighbours.setdefault(a, set()).add(b)
            neighbours.setdefault(b, set()).add(a)
        key = lambda a, b: (a, b) if (a, b) in edges else (b, a)  # noqa: E731
        for i, j in edges:
            for k in neighbours[i] & neighbours[j]:
                c = frozenset({key(i, j), key(j, k), key(i, k)})
                if c not in cycles:
                    cycles[c] = self.discrepancy(i, j, [i, k, j])
                    loops[c] = [i, k, j]
            for k in neighbours[i] - {j}:
                for m in (neighbours[k] & neighbours[j]) - {i, k}:
                    c = frozenset({key(i, j), key(i, k), key(k, m), key(m, j)})
                    if c not in cycles:
                        cycles[c] = self.discrepancy(i, j, [i, k, m, j])
                        loops[c] = [i, k, m, j]

    def count(self, active: set, max_voxels: float):
        """Per active pair: inconsistent and consistent cycles among the active pairs,
        the discrepancies of the inconsistent ones and those cycles."""
        bad = dict.fromkeys(active, 0)
        good = dict.fromkeys(active, 0)
        worst: dict = {e: [] for e in active}
        bad_cycles: dict = {e: [] for e in active}
        for c, d in self.cycles.items():
            if not c <= active:
                continue
            for e in c:
                if d > max_voxels:
                    bad[e] += 1
                    worst[e].append(d)
                    bad_cycles[e].append(c)
                else:
                    good[e] += 1
        return bad, good, worst, bad_cycles

    def support(self, e, c=None) -> float:
        """Geometric support of pair e's own pose (c None) or of the pose cycle c implies."""
        if (e, c) not in self.support_cache:
            i, j = e
            if c is None:
                T = self.pose(i, j)
            else:  # the way round the loop from i to j that avoids the edge (i, j)
                loop = self.loops[c]
                a = loop.index(i)
                turned = loop[a:] + loop[:a]
                path = turned if turned[1] != j else [turned[0]] + turned[:0:-1]
                T = self.compose(path)
            scores = score_alignment(
                self.pre[i], self.pre[j], T, self.align_cfg, scales=self.scales
            )
            self.support_cache[(e, c)] = geometric_support(scores, self.align_cfg)
        return self.support_cache[(e, c)]

    def beaten(self, e, bad_cycles) -> tuple[float, float, float]:
        """(margin, own support, best cycle support) of pair e against its cycles."""
        own = self.support(e)
        tested = sorted(bad_cycles, key=lambda c: sorted(c))[: self.max_tested]
        best = max((self.support(e, c) for c in tested), default=0.0)
        return best - own, own, best

    def beaten_most(self, contradicted: list, bad_cycles: dict) -> tuple:
        """The contradicted pair beaten by the largest margin (a cycle's pose better
        supported, or its own pose not supported at all: a pair put in by hand) and its
        supports; (None, {}) when none is beaten or without ``align_cfg``."""
        if self.align_cfg is None:
            return None, {}
        tests = {e: self.beaten(e, bad_cycles[e]) for e in contradicted}
        flag, _, e = max(
            (tests[e][0] > 0 or tests[e][1] == 0, tests[e][0], e) for e in contradicted
        )
        if not flag:
            return None, {}
        return e, {"own_support": tests[e][1], "best_cycle_support": tests[e][2]}
