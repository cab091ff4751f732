"""Open3D multiway registration as its documentation teaches it (see :mod:`bench.peers`).

- :func:`o3d_prepare` / :func:`o3d_pair` -- the reconstruction system's preprocessing and
  FPFH RANSAC + multiscale point-to-plane ICP of one pair;
- :func:`o3d_optimize` -- ``global_optimization`` of a pose graph;
- :func:`run_open3d_own` -- all of it on its own pairs (odometry + loop closures);
- :func:`run_open3d_fed` -- the pose graph fed mvreg's accepted pairs (and the same
  information matrices converted to GTSAM covariances).
"""

from __future__ import annotations

import time

import numpy as np

from bench.peers.graph import poses_from_tree


def o3d_prepare(points: np.ndarray, v: float, sensor: np.ndarray | None = None) -> dict:
    """The reconstruction system's preprocess_point_cloud + multiscale ICP levels; with
    ``sensor`` (scan frame), normals oriented towards it (:mod:`bench.peers.open3d_tuned`)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    levels = []
    for s in (v, v / 2, v / 4):
        d = pcd.voxel_down_sample(s)
        d.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * s, max_nn=30))
        if sensor is not None:
            d.orient_normals_towards_camera_location(np.asarray(sensor, dtype=np.float64))
        levels.append(d)
    fpfh = reg.compute_fpfh_feature(
        levels[0], o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * v, max_nn=100)
    )
    return {"levels": levels, "fpfh": fpfh}


def o3d_pair(src: dict, tgt: dict, v: float):
    """FPFH RANSAC + multiscale point-to-plane ICP: (ok, T_target_source, information)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    dist = 1.4 * v
    a, b = src["levels"][0], tgt["levels"][0]
    r = reg.registration_ransac_based_on_feature_matching(
        a, b, src["fpfh"], tgt["fpfh"], False, dist,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(100000, 0.999),
    )  # fmt: skip
    T = np.asarray(r.transformation).copy()
    ok = abs(np.trace(T) - 4.0) > 1e-12
    if ok:
        info0 = reg.get_information_matrix_from_point_clouds(a, b, dist, T)
        ok = info0[5, 5] / min(len(a.points), len(b.points)) >= 0.3
    T, _ = multiscale_icp(src, tgt, T, (dist, dist, dist))
    info = reg.get_information_matrix_from_point_clouds(
        src["levels"][-1], tgt["levels"][-1], dist, T
    )
    return bool(ok), T, np.asarray(info)


def multiscale_icp(src: dict, tgt: dict, T: np.ndarray, distances) -> tuple[np.ndarray, float]:
    """Point-to-plane ICP on the three levels (50, 30, 14 iterations), coarse to fine, at
    ``distances`` (one per level): (T_target_source, fitness on the finest level)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    fitness = 0.0
    for k, (dist, iters) in enumerate(zip(distances, (50, 30, 14), strict=True)):
        r = reg.registration_icp(
            src["levels"][k], tgt["levels"][k], dist, T,
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6,
                                       max_iteration=iters),
        )  # fmt: skip
        T, fitness = np.asarray(r.transformation).copy(), float(r.fitness)
    return T, fitness


def o3d_optimize(n: int, edges: list, init: dict[int, np.ndarray], v: float) -> dict:
    """edges: (source, target, T_target_source, info, uncertain). Returns T_world_k."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    keep = sorted(init)
    idx = {k: a for a, k in enumerate(keep)}
    pg = reg.PoseGraph()
    for k in keep:
        pg.nodes.append(reg.PoseGraphNode(init[k]))
    for s, t, T, info, unc in edges:
        if s in idx and t in idx:
            pg.edges.append(reg.PoseGraphEdge(idx[s], idx[t], T, info, uncertain=unc))
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=1.4 * v, edge_prune_threshold=0.25, reference_node=0
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(
            pg,
            reg.GlobalOptimizationLevenbergMarquardt(),
            reg.GlobalOptimizationConvergenceCriteria(),
            option,
        )
    return {k: np.asarray(pg.nodes[idx[k]].pose).copy() for k in keep}


def run_open3d_own(points: list[np.ndarray], v: float, seed: int) -> dict:
    """Open3D multiway registration with its own pairwise stage (all pairs)."""
    import open3d as o3d

    o3d.utility.random.seed(seed)
    n = len(points)
    t0 = time.perf_counter()
    prep = [o3d_prepare(p, v) for p in points]
    t_prep = time.perf_counter() - t0
    edges, pair_s = [], {}
    odometry = np.eye(4)
    nodes = {0: np.eye(4)}
    n_loop = 0
    for s in range(n):
        for t in range(s + 1, n):
            t1 = time.perf_counter()
            ok, T, info = o3d_pair(prep[s], prep[t], v)
            pair_s[(s, t)] = time.perf_counter() - t1
            if t == s + 1:  # odometry case
                odometry = T @ odometry
                nodes[t] = np.linalg.inv(odometry)
                edges.append((s, t, T, info, False))
            elif ok:  # loop closure case
                edges.append((s, t, T, info, True))
                n_loop += 1
    t_pair = time.perf_counter() - t0
    t1 = time.perf_counter()
    T_world = o3d_optimize(n, edges, nodes, v)
    t_glob = time.perf_counter() - t1
    # Diagnostic variant (not in the tutorial): every edge a prunable loop closure.
    t1 = time.perf_counter()
    T_unc = o3d_optimize(n, [(s, t, T, i, True) for s, t, T, i, _ in edges], nodes, v)
    t_unc = time.perf_counter() - t1
    chain_pair = t_prep + sum(pair_s[(k, k + 1)] for k in range(n - 1))
    return {
        "T_all_uncertain": T_unc,
        "global_s_all_uncertain": t_unc,
        "T": T_world,
        "pairwise_s": t_pair,
        "global_s": t_glob,
        "chain_T": nodes,
        "chain_pairwise_s": chain_pair,
        "prep": prep,
        "edge_list": [(s, t, T, unc) for s, t, T, _, unc in edges],
        "edges": f"{n - 1} odometry + {n_loop} loop closures",
    }


def run_open3d_fed(n, rel: dict, prep, v: float, pairwise_s: float) -> dict:
    """Open3D's pose graph optimisation on mvreg's accepted pairs (same edges)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    t0 = time.perf_counter()
    edges = []
    for (i, j), T in rel.items():  # T_i_j maps j (source) into i (target)
        info = reg.get_information_matrix_from_point_clouds(
            prep[j]["levels"][-1], prep[i]["levels"][-1], 1.4 * v, T
        )
        edges.append((j, i, T, np.asarray(info), abs(i - j) != 1))
    t_info = time.perf_counter() - t0
    # The same information matrices for GTSAM: Open3D's are for a left perturbation of
    # T_target_source in the target frame; GTSAM's between factor perturbs on the right,
    # xi_left = Ad(T) xi_right, so Lambda_right = Ad^T Lambda_left Ad.
    import gtsam

    cov = {}
    for (i, j), T in rel.items():
        info = next(e[3] for e in edges if e[0] == j and e[1] == i)
        ad = gtsam.Pose3(T).AdjointMap()
        cov[(i, j)] = np.linalg.inv(ad.T @ info @ ad)
    init = poses_from_tree(n, rel)  # spanning tree (the tutorial's odometry chain may break)
    t1 = time.perf_counter()
    T_world = o3d_optimize(n, edges, init, v)
    return {
        "T": T_world,
        "pairwise_s": pairwise_s + t_info,
        "global_s": time.perf_counter() - t1,
        "edges": f"{len(rel)} (mvreg's accepted pairs)",
        "cov": cov,
    }
