"""Feature matches between two scans: mutual nearest neighbours of FPFH descriptors.

Takes two preprocessed scans (their feature-level FPFH descriptors) and a
:class:`FeatureBasis`; returns index pairs into the two scans' feature-level points.
The descriptors are compared after a PCA to a few dimensions (``AlignConfig.feature_dims``),
fitted on all scans of a run (so that every pair is compared in the same space) or on one
pair's alone. Deterministic; reduced descriptors and their KD-trees are cached on the
scan per basis. Measurements behind the defaults: ``docs/design/pairwise.md``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mvreg.pairwise.preprocess import PreprocessedScan


@dataclass(frozen=True)
class FeatureBasis:
    """PCA of FPFH descriptors: ``(f - mean) @ basis`` gives the reduced descriptor."""

    mean: np.ndarray
    basis: np.ndarray

    @classmethod
    def fit(cls, feature_sets: Sequence[np.ndarray], dims: int = 16) -> FeatureBasis:
        both = np.vstack(feature_sets)
        mean = both.mean(axis=0)
        _, _, vt = np.linalg.svd(both - mean, full_matrices=False)
        return cls(mean, vt[: min(dims, both.shape[1])].T.copy())


def reduced_tree(pre: PreprocessedScan, basis: FeatureBasis) -> tuple[np.ndarray, cKDTree]:
    """(N, dims) reduced descriptors of ``pre`` and their KD-tree, cached per basis."""
    cached = pre._cache.get("reduced_features")
    if cached is None or cached[0] is not basis:  # holding the basis keeps `is` meaningful
        reduced = (pre.features - basis.mean) @ basis.basis
        cached = (basis, reduced, cKDTree(reduced))
        pre._cache["reduced_features"] = cached
    return cached[1], cached[2]


def feature_matches(
    pre_i: PreprocessedScan, pre_j: PreprocessedScan, basis: FeatureBasis, eps: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours in (reduced) descriptor space -> (idx_i, idx_j), int64.

    ``eps``: approximate search (``cKDTree.query``), distances within a factor 1 + eps.
    """
    fi, tree_i = reduced_tree(pre_i, basis)
    fj, tree_j = reduced_tree(pre_j, basis)
    _, nn_ji = tree_i.query(fj, eps=eps)
    # Only the descriptors of i that some j hit can be mutual: query those alone (the
    # same answers; the model of many scans against one scan no longer costs its size).
    hit, where = np.unique(nn_ji, return_inverse=True)
    _, back = tree_j.query(fi[hit], eps=eps)
    idx_j = np.flatnonzero(back[where] == np.arange(len(fj)))
    return nn_ji[idx_j].astype(np.int64), idx_j.astype(np.int64)
