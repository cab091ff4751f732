"""Open3D multiway registration, tuned (issue 13, item 4): what a careful Open3D user
would build, rather than the tutorial's settings of :mod:`bench.peers.open3d`.

Per scan (:func:`bench.peers.open3d.o3d_prepare` given the sensor): voxel levels ``v``,
``v/2``, ``v/4`` (``v`` = mvreg's feature voxel of the run, the same for every method); normals (radius 2 voxels, 30
neighbours) **oriented towards the sensor**, FPFH (radius 5 ``v``) on the coarse level.
Per pair (:func:`align`), every pair: RANSAC on mutual FPFH matches (distance 1.5 ``v``,
edge-length and distance checkers, and a normal checker, meaningful now that normals
are oriented; 100k iterations, confidence 0.999), then multiscale point-to-plane ICP
(1.5 ``v``, 0.75 ``v``, 0.375 ``v`` on the three levels), the information matrix and the
overlap (``info[5,5] / min(#points)``, Open3D's reconstruction system's measure) on the
finest level.
Graph (:func:`run_open3d_tuned`): pairs overlapping at least 0.3 (the reconstruction
system's threshold) are edges; the **maximum spanning tree of their ICP fitness** is
certain (``uncertain=False``), every other edge a prunable loop closure; initial poses
along the tree; ``global_optimization`` (Levenberg-Marquardt, ``edge_prune_threshold``
0.25, correspondence distance 1.5 ``v``). Scans outside the tree's component are not
registered; Open3D has no verification, so every other scan counts as registered.

Sensor positions: the true ones where the data set knows them (``synth.json``; a scan
in its scanner's frame has it at the origin), else mvreg's own estimate from the point
grid (:func:`mvreg.pairwise.viewpoint.estimate_viewpoint`), else the scan frame's origin.
"""

from __future__ import annotations

import time

import numpy as np

from bench.peers.graph import poses_from_tree
from bench.peers.open3d import multiscale_icp, o3d_prepare

MIN_OVERLAP = 0.3


def align(src: dict, tgt: dict, v: float, seed: int) -> dict:
    """RANSAC + multiscale point-to-plane ICP of ``src`` onto ``tgt``: T_target_source,
    ICP fitness, overlap and information matrix (finest level)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    o3d.utility.random.seed(seed)
    dist = 1.5 * v
    a, b = src["levels"][0], tgt["levels"][0]
    r = reg.registration_ransac_based_on_feature_matching(
        a, b, src["fpfh"], tgt["fpfh"], True, dist,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         reg.CorrespondenceCheckerBasedOnDistance(dist),
         reg.CorrespondenceCheckerBasedOnNormal(np.radians(30.0))],
        reg.RANSACConvergenceCriteria(100000, 0.999),
    )  # fmt: skip
    T = np.asarray(r.transformation).copy()
    T, fitness = multiscale_icp(src, tgt, T, (dist, dist / 2, dist / 4))
    fine_a, fine_b = src["levels"][-1], tgt["levels"][-1]
    info = np.asarray(reg.get_information_matrix_from_point_clouds(fine_a, fine_b, dist / 4, T))
    overlap = float(info[5, 5]) / max(1, min(len(fine_a.points), len(fine_b.points)))
    return {"T": T, "fitness": fitness, "overlap": overlap, "info": info}


def maximum_spanning_tree(n: int, weights: dict[tuple[int, int], float]) -> set[tuple[int, int]]:
    """Edges (i, j) of a maximum spanning forest of ``weights`` (Kruskal)."""
    parent = list(range(n))

    def root(k):
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    tree = set()
    for (i, j), _ in sorted(weights.items(), key=lambda kv: (-kv[1], kv[0])):
        ri, rj = root(i), root(j)
        if ri != rj:
            parent[ri] = rj
            tree.add((i, j))
    return tree


def run_open3d_tuned(
    points: list[np.ndarray], v: float, sensors: list[np.ndarray], seed: int
) -> dict:
    """The tuned pipeline on scans ``points`` (their own frames): ``T`` (index ->
    T_world_scan, the registered scans), seconds, edge counts."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    n = len(points)
    t0 = time.perf_counter()
    prep = [o3d_prepare(p, v, c) for p, c in zip(points, sensors, strict=True)]
    pairs = {}
    for i in range(n):
        for j in range(i + 1, n):  # j (source) onto i (target): T_i_j
            pairs[(i, j)] = align(prep[j], prep[i], v, seed * 100003 + i * n + j)
    t_pair = time.perf_counter() - t0
    t1 = time.perf_counter()
    edges = {k: p for k, p in pairs.items() if p["overlap"] >= MIN_OVERLAP}
    tree = maximum_spanning_tree(n, {k: p["fitness"] for k, p in edges.items()})
    rel = {k: edges[k]["T"] for k in tree}
    init = poses_from_tree(n, rel) if rel else {0: np.eye(4)}  # the largest component
    keep = sorted(init)
    idx = {k: a for a, k in enumerate(keep)}
    pg = reg.PoseGraph()
    for k in keep:
        pg.nodes.append(reg.PoseGraphNode(init[k]))
    for (i, j), p in edges.items():
        if i in idx and j in idx:
            pg.edges.append(reg.PoseGraphEdge(idx[j], idx[i], p["T"], p["info"],
                                              uncertain=(i, j) not in tree))  # fmt: skip
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=1.5 * v / 4, edge_prune_threshold=0.25, reference_node=0
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(
            pg, reg.GlobalOptimizationLevenbergMarquardt(),
            reg.GlobalOptimizationConvergenceCriteria(), option,
        )  # fmt: skip
    T = {k: np.asarray(pg.nodes[idx[k]].pose).copy() for k in keep}
    return {
        "T": T,
        "pairwise_s": t_pair,
        "global_s": time.perf_counter() - t1,
        "edges": f"{len(tree)} tree + {len(edges) - len(tree)} prunable of {len(pairs)} pairs",
        "pairs": pairs,
        "tree": tree,
    }
