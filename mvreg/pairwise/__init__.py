"""From scans to a patch problem: preprocess, candidate pairs, pairwise alignment, tracks.

    scales = derive_scales(scans, cfg.preprocess)
    pre = preprocess_all(scans, scales.voxel, cfg.preprocess)
    scales = with_noise(scales, pre)
    results = align_pairs(pre, candidate_pairs(pre), cfg.align, seed=0, scales=scales)
    results = connect_unconnected(pre, results, cfg.align, cfg.search, scales=scales)
    tracks = build_tracks(pre, results, cfg.tracks, scales=scales)  # tracks.problem

Modules: :mod:`.preprocess` (voxel levels, normals, FPFH, scales), :mod:`.candidates`,
:mod:`.features`, :mod:`.hypotheses` (RANSAC), :mod:`.icp`, :mod:`.scoring`,
:mod:`.decision` (acceptance rule, verification), :mod:`.result` (PairResult),
:mod:`.aligners` (the aligner interface and registry), :mod:`.align` (all pairs),
:mod:`.search` (scans left unconnected), :mod:`.consistency` (cycle check),
:mod:`.correspondences`, :mod:`.tracks`. Design notes: ``docs/design/pairwise.md``.
"""

from mvreg.pairwise.align import align_pairs, reject_relative_outliers
from mvreg.pairwise.aligners import (
    ALIGNERS,
    PairwiseAligner,
    align_pair,
    make_aligner,
    register_aligner,
)
from mvreg.pairwise.candidates import candidate_pairs
from mvreg.pairwise.correspondences import mutual_correspondences
from mvreg.pairwise.decision import decide, geometric_support, rescore, verify
from mvreg.pairwise.icp import fine_icp, icp_point_to_plane, nearest_with_normals
from mvreg.pairwise.preprocess import (
    PreprocessedScan,
    derive_scales,
    derive_voxel_size,
    preprocess,
    preprocess_all,
    resample,
    scan_scales,
    with_noise,
)
from mvreg.pairwise.result import PairResult, pair_seed
from mvreg.pairwise.scoring import score_alignment
from mvreg.pairwise.search import connect_unconnected
from mvreg.pairwise.tracks import (
    Tracks,
    build_tracks,
    pair_correspondences,
    tracks_from_correspondences,
)

__all__ = [
    "ALIGNERS",
    "PairResult",
    "PairwiseAligner",
    "PreprocessedScan",
    "Tracks",
    "align_pair",
    "align_pairs",
    "build_tracks",
    "candidate_pairs",
    "connect_unconnected",
    "decide",
    "derive_scales",
    "derive_voxel_size",
    "fine_icp",
    "geometric_support",
    "icp_point_to_plane",
    "make_aligner",
    "mutual_correspondences",
    "nearest_with_normals",
    "pair_correspondences",
    "pair_seed",
    "preprocess",
    "preprocess_all",
    "register_aligner",
    "reject_relative_outliers",
    "resample",
    "rescore",
    "scan_scales",
    "score_alignment",
    "tracks_from_correspondences",
    "verify",
    "with_noise",
]
