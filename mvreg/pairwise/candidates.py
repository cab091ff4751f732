"""Stage 2: which scan pairs to align.

Up to ``all_pairs_max_scans`` scans every pair is tried (M (M - 1) / 2 alignments). Above
it each scan is paired with its ``neighbours_per_scan`` most similar scans by a global
descriptor -- the mean and standard deviation of its FPFH histograms, square-rooted
(Hellinger) so that a Euclidean distance compares them -- so the cost grows like M k.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from mvreg.config.pairs import PairsConfig
from mvreg.pairwise.preprocess import PreprocessedScan


def global_descriptor(pre: PreprocessedScan) -> np.ndarray:
    """(66,) pooled FPFH: Hellinger-mapped mean and standard deviation of the histograms."""
    f = pre.features / np.maximum(pre.features.sum(axis=1, keepdims=True), 1e-12)
    return np.concatenate([np.sqrt(f.mean(axis=0)), np.sqrt(f.std(axis=0))])


def candidate_pairs(
    pre: Sequence[PreprocessedScan], cfg: PairsConfig | None = None
) -> list[tuple[int, int]]:
    """Scan index pairs (i, j), i < j, in lexicographic order."""
    cfg = cfg or PairsConfig()
    m = len(pre)
    if m <= cfg.all_pairs_max_scans:
        return [(i, j) for i in range(m) for j in range(i + 1, m)]
    desc = np.stack([global_descriptor(p) for p in pre])
    k = min(cfg.neighbours_per_scan, m - 1)
    _, nn = cKDTree(desc).query(desc, k=k + 1)
    pairs = set()
    for i in range(m):
        for j in nn[i]:
            if j != i and j < m:
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)
