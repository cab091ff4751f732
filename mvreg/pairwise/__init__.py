"""From scans to a patch problem: preprocess, candidate pairs, pairwise alignment, tracks.

v = derive_voxel_size(scans)
pre = [preprocess(scan, v) for scan in scans]
results = align_pairs(pre, candidate_pairs(pre), seed=0)
tracks = build_tracks(pre, results)          # tracks.problem is a PatchProblem
"""

from mvreg.pairwise.align import AlignConfig, PairResult, align_pair, align_pairs, score_alignment
from mvreg.pairwise.candidates import PairsConfig, candidate_pairs
from mvreg.pairwise.correspondences import mutual_correspondences
from mvreg.pairwise.preprocess import (
    PreprocessConfig,
    PreprocessedScan,
    derive_voxel_size,
    preprocess,
    preprocess_all,
    resample,
)
from mvreg.pairwise.tracks import (
    Tracks,
    TracksConfig,
    build_tracks,
    pair_correspondences,
    tracks_from_correspondences,
)

__all__ = [
    "AlignConfig",
    "PairResult",
    "PairsConfig",
    "PreprocessConfig",
    "PreprocessedScan",
    "Tracks",
    "TracksConfig",
    "align_pair",
    "align_pairs",
    "build_tracks",
    "candidate_pairs",
    "derive_voxel_size",
    "mutual_correspondences",
    "preprocess_all",
    "pair_correspondences",
    "preprocess",
    "resample",
    "score_alignment",
    "tracks_from_correspondences",
]
