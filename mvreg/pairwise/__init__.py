"""From scans to a patch problem: preprocess, candidate pairs, pairwise alignment, tracks.

v = derive_voxel_size(scans)
pre = [preprocess(scan, v) for scan in scans]
results = align_pairs(pre, candidate_pairs(pre), seed=0)
tracks = build_tracks(pre, results)          # tracks.problem is a PatchProblem
"""

from mvreg.pairwise.align import PairResult, align_pair, align_pairs, score_alignment
from mvreg.pairwise.candidates import candidate_pairs
from mvreg.pairwise.correspondences import mutual_correspondences
from mvreg.pairwise.preprocess import (
    PreprocessedScan,
    derive_voxel_size,
    preprocess,
    preprocess_all,
    resample,
)
from mvreg.pairwise.tracks import (
    Tracks,
    build_tracks,
    pair_correspondences,
    tracks_from_correspondences,
)

__all__ = [
    "PairResult",
    "PreprocessedScan",
    "Tracks",
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
