"""mvreg's benchmarks and paper experiments, on the public API of :mod:`mvreg`.

Each module runs one benchmark and writes its report (markdown, json, plots); the thin
entry points in ``scripts/`` parse the command line and call ``main(argv)`` here.
Shared helpers (machine description, the bunny's ground truth) are in :mod:`bench.common`.

- :mod:`bench.peers` -- mvreg vs Open3D multiway, GTSAM and chaining (``bench_peers.py``);
- :mod:`bench.register`, :mod:`bench.sequence` -- accuracy and time of ``register``;
- :mod:`bench.solver`, :mod:`bench.solvers` -- the global solvers on patch problems;
- :mod:`bench.papers` -- figures of the papers mvreg implements.
"""
