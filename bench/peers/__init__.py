#!/usr/bin/env python3
"""mvreg side by side with the tools users would pick instead (issue 4, "Peer benchmark").

Same inputs, same machine, same run. Per dataset, every method gets the same raw scans:

* ``mvreg`` -- ``mvreg.pipeline.register`` with default settings (global solver reg-admm);
* ``mvreg/<solver>`` -- the same pipeline with each other registered global solver
  (``solve.solver``), reusing the default run's preprocessing and pairwise results through
  the public staged API (:mod:`bench.peers.mvreg_run`; so only the global stage differs); ``mvreg/no-refine`` -- defaults without the
  multiview-ICP refinement rounds and the joint ICP (global solve + robust re-weighting
  only);
* ``open3d`` -- Open3D multiway registration as its documentation teaches it (the
  multiway-registration tutorial + the reconstruction system's ``register_fragments``):
  voxel down-sampling, normals (radius 2v, 30 nn), FPFH (radius 5v, 100 nn), RANSAC on
  feature matches (distance 1.4v, edge-length 0.9 and distance checkers, 100,000 iterations,
  confidence 0.999), multiscale point-to-plane ICP (v, v/2, v/4; 50/30/14 iterations;
  distance 1.4v), information matrices from ``get_information_matrix_from_point_clouds``;
  consecutive scans become odometry edges (``uncertain=False``), the other pairs loop
  closures (``uncertain=True``) when RANSAC succeeded and the information check of
  ``register_fragments`` passes (``info[5, 5] / min(#points) >= 0.3``); then
  ``global_optimization`` with ``GlobalOptimizationLevenbergMarquardt``, default
  ``GlobalOptimizationConvergenceCriteria`` and
  ``GlobalOptimizationOption(max_correspondence_distance=1.4v, edge_prune_threshold=0.25,
  reference_node=0)``. The voxel v is the one mvreg derives for the data (same scale for all);
* ``open3d/all-uncertain`` -- diagnostic, not in the tutorial: the same edges and start,
  but every edge (odometry too) a prunable loop closure;
* ``open3d/mvreg-pairs`` -- the same pose graph optimisation fed mvreg's accepted pairs
  (mvreg's pairwise transforms, Open3D information matrices on its own clouds, edges
  between consecutive scans as odometry, start from a spanning tree), so the global
  stages see identical edges;
* ``gtsam`` -- GTSAM Shonan rotation averaging (``ShonanAveraging3.run`` on the relative
  rotations of mvreg's accepted pairs, random initialisation, p = 3..10), translations
  first from the linear least squares of GTSAM's Shonan example, then a GTSAM pose-graph
  solve (``BetweenFactorPose3``, ``LevenbergMarquardtOptimizer``) initialised with them;
  edge covariances = the inverse of the same Open3D information matrices, moved to GTSAM's
  right-perturbation tangent with the adjoint;
* ``chain`` -- pairwise registrations composed in scan order (scan k+1 to scan k, what a
  user does by hand): ``chain/mvreg-pairs`` with mvreg's pairwise transforms,
  ``chain/open3d-pairs`` with Open3D's (= the odometry initialisation of its pose graph).

Datasets: the ten real Stanford Bunny scans (truth ``bun.conf``), data_synth scans of each
mesh in ../shared/data/meshes (12 views, random frames; clean, 0.5% range noise, 10%
outliers), and synthetic patch problems (``data_synth.problems.make_problem``) where
mvreg's matrix-free REG-ADMM (``solve(problem, method="matrix-free")``) meets GTSAM
Shonan + pose graph fed relative poses from Kabsch on each pair's shared nodes (covariance
from the fit residual and the nodes' spread). Patch cases run in subprocesses with a time
limit. The other mvreg solvers run on the bunny and the clean synthetic sets only
(``--all-solvers``: everywhere). Rows are checkpointed after each dataset (``--resume``).

Writes docs/benchmarks/peers.md, peers_*.png and peers.json (raw numbers).

Modules: :mod:`.mvreg_run` (mvreg and its variants), :mod:`.open3d`, :mod:`.gtsam`,
:mod:`.chaining` (one per peer); :mod:`.graph` (spanning trees); :mod:`.datasets` (every
method on a folder of scans), :mod:`.patches` (patch problems); :mod:`.report`,
:mod:`.plots`, :mod:`.findings` (peers.md); :mod:`.settings`; :mod:`.cli` (the options).

    OPENBLAS_NUM_THREADS=1 python scripts/bench_peers.py              # full
    OPENBLAS_NUM_THREADS=1 python scripts/bench_peers.py --quick      # bunny + one mesh, M <= 1000
"""
