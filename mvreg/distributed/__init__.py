"""Per-scan and per-pair tasks on a Dask distributed cluster (optional).

The default executor of a run is in-process threads (:class:`mvreg.executor.ThreadExecutor`,
``threads``; nothing to start). ``workers`` starts a local cluster of that many worker
processes; ``scheduler`` connects to a running one (``dask scheduler`` and ``dask worker
ADDRESS`` on other machines). Either way the run's task executor is a
:class:`DaskExecutor`: preprocessing (and the voxel measurement before it) per scan and
pairwise alignment per candidate pair run as Dask tasks; everything else stays in-process.

    with open_executor(threads=2, workers=2) as ex:   # a LocalCluster of 2 processes
        pre = preprocess_all(scans, voxel, cfg, ex)

``dask`` and ``distributed`` are imported only when a cluster is used.
"""

from __future__ import annotations

from mvreg.distributed.executor import DaskExecutor, open_executor, task_size

__all__ = ["DaskExecutor", "open_executor", "task_size"]
