"""``rotation-search``: align two scans by trying start rotations, no features needed.

For scans whose FPFH descriptors do not discriminate (flat faces of a CAD part) and
feature RANSAC therefore fails. Scan j is placed on scan i from ``len(starts)`` start
rotations (:func:`rotation_starts`: the 60 rotations of the icosahedral group, each also
turned by ``search.offset_deg`` about x, y and z: 240 starts, no rotation farther than
about 25 degrees from one), centroids on centroids. Each start runs
``search.screen_iterations`` iterations of feature-level point-to-plane ICP per distance
of ``search.screen_distances_voxels`` on at most ``search.screen_source_points`` points
and must pass the loosened acceptance rule (:func:`~mvreg.pairwise.decision.screen`,
including both free-space tests, which reject the slides and flips that fit the planes
locally). The distinct survivors (not within a feature voxel of each other) go through
the full verification of ordinary pairs (:func:`~mvreg.pairwise.decision.verify`), and
the best supported accepted one is kept.

The starts are screened on the aligner's ``executor``; deterministic whatever it is
(fixed starts, results in start order; ``guess`` and ``seed`` unused). Stats:
``search`` (True), ``search_survivors``, ``hypotheses_tried``, ``hypotheses_accepted``.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial.transform import Rotation

from mvreg.config.align import AlignConfig, SearchConfig
from mvreg.executor import Executor
from mvreg.pairwise.aligners.base import BaseAligner, register_aligner
from mvreg.pairwise.decision import choose, screen, verify
from mvreg.pairwise.hypotheses import distinct_poses, scan_extent
from mvreg.pairwise.icp import feature_level_tree, icp_point_to_plane_batch
from mvreg.pairwise.preprocess import PreprocessedScan
from mvreg.pairwise.result import PairResult, pair_result
from mvreg.scales import Scales


def rotation_starts(offset_deg: float = 20.0) -> np.ndarray:
    """(240, 3, 3): the icosahedral group, and its copies turned about x, y and z."""
    group = Rotation.create_group("I").as_matrix()
    a = np.radians(offset_deg)
    turns = Rotation.from_rotvec([[0, 0, 0], [a, 0, 0], [0, a, 0], [0, 0, a]]).as_matrix()
    return np.einsum("aij,bjk->abik", group, turns).reshape(-1, 3, 3)


@register_aligner("rotation-search")
class RotationSearchAligner(BaseAligner):
    """ICP from every start rotation, then the acceptance rule (module docstring)."""

    def align(self, pre_i, pre_j, guess=None, seed=0, *, i=0, j=1) -> PairResult:
        """Align j to i from every start rotation; accepted or not."""
        cfg, search = self.cfg, self.search
        start = time.perf_counter()
        scales = self.scales_for(pre_i)
        v = scales.voxel
        ci = pre_i.points.mean(axis=0)
        cj, radius = scan_extent(pre_j.points)
        stride = max(1, len(pre_j.points) // search.screen_source_points)
        src, src_n = pre_j.points[::stride], pre_j.normals[::stride]
        tree = feature_level_tree(pre_i)

        starts = rotation_starts(search.offset_deg)
        T = np.tile(np.eye(4), (len(starts), 1, 1))
        T[:, :3, :3] = starts
        T[:, :3, 3] = ci - starts @ cj
        for k, dist in enumerate(search.screen_distances_voxels):  # all starts at once
            thin = 3 if k == 0 else 1  # the widest stage on a third of the points
            T = icp_point_to_plane_batch(
                src[::thin], src_n[::thin], pre_i.points, pre_i.normals, tree, T, dist * v,
                search.screen_iterations, cfg.icp_min_normal_cos, self.executor.workers,
            )  # fmt: skip
            T = np.stack(distinct_poses(list(T), 0.25 * v, cj, radius))  # met in one basin

        def screened(M: np.ndarray):
            return M if screen(pre_i, pre_j, M, cfg, scales) else None

        survivors = [M for M in self.executor.map(screened, list(T)) if M is not None]
        tried = [
            verify(pre_i, pre_j, T, cfg, scales) for T in distinct_poses(survivors, v, cj, radius)
        ]
        stats = {"search": True, "search_survivors": len(survivors)}
        if tried:
            T, reason, scores, _ = choose(tried, cfg, stats)
        else:
            stats["hypotheses_tried"] = stats["hypotheses_accepted"] = 0
            T, reason, scores = np.eye(4), "rotation search found no alignment", None
        return pair_result(
            pre_i, pre_j, i, j, T, reason, scores, stats, start, fine_voxel=scales.fine_voxel
        )


def search_pair(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    cfg: AlignConfig | None = None,
    search: SearchConfig | None = None,
    i: int = 0,
    j: int = 1,
    executor: Executor | int = 2,
    *,
    scales: Scales | None = None,
) -> PairResult:
    """Align j to i with ``rotation-search`` (module docstring); accepted or not."""
    aligner = RotationSearchAligner(cfg, search, scales=scales, executor=executor)
    return aligner.align(pre_i, pre_j, i=i, j=j)
