"""GTSAM: Shonan rotation averaging, linear translations, then a Pose3 pose-graph solve."""

from __future__ import annotations

import time

import numpy as np

from bench.peers.graph import largest_component, main_root


def gtsam_solve(n: int, rel: dict, cov: dict) -> dict:
    """Shonan averaging on the relative rotations, linear translations, Pose3 LM.

    rel: {(i, j): T_i_j} with T_i_j = T_world_i^-1 T_world_j (GTSAM's between(X_i, X_j)).
    cov: {(i, j): (6, 6) covariance of the edge in GTSAM's Pose3 tangent (omega, v), right
    perturbation of T_i_j}. Returns T_world_k for the component of node 0, stage times.
    """
    import gtsam

    reach, _ = largest_component(n, list(rel), main_root(n, list(rel)))
    keep = sorted(reach)
    key = {k: a for a, k in enumerate(keep)}
    E = [(key[i], key[j], T) for (i, j), T in rel.items() if i in key and j in key]
    t0 = time.perf_counter()
    unit = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    meas = [gtsam.BinaryMeasurementRot3(i, j, gtsam.Rot3(T[:3, :3]), unit) for i, j, T in E]
    params = gtsam.ShonanAveragingParameters3(gtsam.LevenbergMarquardtParams.CeresDefaults())
    shonan = gtsam.ShonanAveraging3(meas, params)
    initial = shonan.initializeRandomly()
    rots, min_eig = shonan.run(initial, 3, 10)
    threshold = params.getOptimalityThreshold()
    t_rot = time.perf_counter() - t0
    t1 = time.perf_counter()
    # Translations given rotations (GTSAM's ShonanAveragingCLI.estimate_poses_given_rot).
    g = gtsam.GaussianFactorGraph()
    model = gtsam.noiseModel.Unit.Create(3)
    g.add(0, np.eye(3), np.zeros(3), model)
    for i, j, T in E:
        g.add(j, np.eye(3), i, -np.eye(3), rots.atRot3(i).rotate(T[:3, 3]), model)
    tr = g.optimize()
    init = gtsam.Values()
    for k in range(len(keep)):
        init.insert(k, gtsam.Pose3(rots.atRot3(k), tr.at(k)))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, init.atPose3(0), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    for (a_, b_), T in rel.items():
        if a_ in key and b_ in key:
            noise = gtsam.noiseModel.Gaussian.Covariance(cov[(a_, b_)])
            graph.add(gtsam.BetweenFactorPose3(key[a_], key[b_], gtsam.Pose3(T), noise))
    out = gtsam.LevenbergMarquardtOptimizer(
        graph, init, gtsam.LevenbergMarquardtParams()
    ).optimize()
    t_tr = time.perf_counter() - t1
    T_world = {keep[k]: out.atPose3(k).matrix() for k in range(len(keep))}
    return {
        "T": T_world,
        "rotation_s": t_rot,
        "translation_s": t_tr,
        "R_shonan": {keep[k]: rots.atRot3(k).matrix() for k in range(len(keep))},
        "min_eig": float(min_eig),
        "certified": bool(min_eig > threshold),
    }


# ------------------------------------------------------------------------ scan datasets
