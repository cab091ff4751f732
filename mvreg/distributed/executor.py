"""DaskExecutor: the :class:`~mvreg.executor.Executor` protocol on a Dask cluster.

What a task carries: :func:`mvreg.executor.map_shared` hands over the data every task reads
(the run's preprocessed scans and the aligner) once; it is pickled, keyed by the SHA-256
of its bytes, and scattered to every worker (``broadcast``) under that key. A task is then
``run_task(fn, label, <key>, item)``: a module-level function (pickled by reference), a
short label, the key and a small item (a pair of scan indices). An item larger than
:data:`SCATTER_ITEM_BYTES` (a raw scan to preprocess) is scattered on its own, also by
content key, to one worker, so that two stages reading it (the voxel measurement and
preprocessing) ship it once. Worker-side caches (KD-trees, Open3D clouds) are rebuilt
lazily on each worker from the arrays and kept with the scattered object there.

Determinism: results come back in the order of the items, and every task's randomness
comes from the run's seed and the task's item (``pair_seed(seed, i, j)``), never from the
worker or the order tasks ran in; worker processes started by a nanny run BLAS on one
thread (Dask's default environment). So poses are bit-identical to the in-process run.

Failures: a worker lost mid-task has its tasks rescheduled on the others by the scheduler
(up to ``distributed.scheduler.allowed-failures`` times, default 3); scattered data has no
lineage, so when every worker holding it is lost the tasks reading it are cancelled: a
:class:`~mvreg.errors.TaskError` says so, and the next call scatters the data again (under
the key with a send count appended, so a release of the lost copy still in flight at the
scheduler cannot take the new one); a
task that raises is not retried (the same seed gives the same error) and comes back as a
:class:`~mvreg.errors.TaskError` naming the scan or pair; an interrupt (Ctrl-C) while
waiting cancels every task of the call, and :meth:`DaskExecutor.close` closes the client
and the local cluster it started (never a cluster it only connected to).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import pickle
from collections.abc import Callable, Iterable, Iterator
from functools import partial
from typing import Any

from mvreg.errors import ConfigError, MvregError, TaskError
from mvreg.executor import ThreadExecutor, run_task

LOST_DATA = (
    "the data it reads was lost (every worker holding it died, or it was released); "
    "running the command again sends it anew"
)

KEEP_REPLICAS = {"distributed.scheduler.active-memory-manager.start": False}
"""Dask configuration of the local clusters started here: no Active Memory Manager. Its
default policy (ReduceReplicas, every 2 s) drops the copies of the broadcast scans that no
waiting task needs, so the workers fetch them from each other again, and a worker that dies
may take the last copy with it (scattered data has no lineage)."""

SCATTER_ITEM_BYTES = 64 * 1024
"""Items whose pickle is larger than this are scattered once by content key, not sent
with their task."""


def content_key(obj: Any, prefix: str = "mvreg-data") -> tuple[str, int]:
    """(``prefix-<sha256 of the pickle>``, pickled size in bytes) of ``obj``."""
    blob = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    return f"{prefix}-{hashlib.sha256(blob).hexdigest()[:40]}", len(blob)


def task_size(fn: Callable, label: str, ref: Any, item: Any) -> int:
    """Pickled bytes of one task as :class:`DaskExecutor` submits it (``ref``: the key
    string of the shared data, or the item itself when it is sent inline)."""
    import cloudpickle

    return len(cloudpickle.dumps((partial(run_task, fn), label, ref, item)))


class DaskExecutor:
    """Runs tasks on a ``distributed.Client``; ``map`` / ``map_shared`` return results in
    the order of the items (module docstring). ``workers``: the cluster's worker count when
    it was opened. ``owns_cluster``: close the cluster (a LocalCluster) with the executor.

    ``task_bytes``: the largest pickled task of the last ``map_shared`` call
    (:func:`task_size`), ``shared_bytes``: the pickled size of its shared data.
    """

    def __init__(self, client, cluster=None, *, owns_cluster: bool = False):
        self.client = client
        self.cluster = cluster
        self.owns_cluster = owns_cluster
        self.workers = max(1, len(client.scheduler_info().get("workers", {})))
        self.task_bytes = 0
        self.shared_bytes = 0
        self._data: dict[str, Any] = {}  # content key -> Future, for the executor's life
        self._sends: dict[str, int] = {}  # content key -> times scattered (resends renamed)

    @classmethod
    def local(cls, workers: int, threads_per_worker: int = 1) -> DaskExecutor:
        """Start a ``LocalCluster`` of ``workers`` worker processes (no dashboard, no
        Active Memory Manager: :data:`KEEP_REPLICAS`)."""
        import dask
        from distributed import Client, LocalCluster

        from mvreg.distributed.plugins import IgnoreInterrupt

        if workers < 1:
            raise ConfigError(f"workers must be >= 1, got {workers}")
        cluster = None
        try:
            with dask.config.set(KEEP_REPLICAS):
                cluster = LocalCluster(
                    n_workers=workers,
                    threads_per_worker=threads_per_worker,
                    processes=True,
                    dashboard_address=None,
                    # no dashboard; the scheduler's HTTP routes on a free local port
                    scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
                    silence_logs=logging.CRITICAL,  # shutdown chatter; task errors come back
                )
            client = Client(cluster)
            client.register_plugin(IgnoreInterrupt(), name="mvreg-ignore-sigint")
        except BaseException:
            if cluster is not None:
                cluster.close()
            raise
        return cls(client, cluster, owns_cluster=True)

    @classmethod
    def connect(cls, address: str, timeout: float = 10.0) -> DaskExecutor:
        """Connect to a running scheduler and wait (up to ``timeout`` s) for a worker."""
        from distributed import Client

        try:
            client = Client(address, timeout=timeout)
        except (OSError, TimeoutError, ValueError) as e:
            raise ConfigError(f"scheduler {address}: cannot connect ({e})") from None
        try:
            client.wait_for_workers(1, timeout=timeout)
        except (OSError, TimeoutError) as e:
            client.close()
            raise ConfigError(f"scheduler {address}: no worker joined in {timeout:g} s") from e
        return cls(client)

    def share(self, obj: Any, broadcast: bool = True):
        """A Future of ``obj`` on the cluster, under its content key; the same content is
        sent once for the executor's life (``broadcast``: to every worker)."""
        key, size = content_key(obj)
        future = self._data.get(key)
        if future is None or future.status != "finished":  # not sent yet, or lost since
            # Sent again under a new name: the scheduler may still be releasing the lost
            # copy, and a release landing after the new scatter took it too (a CI run:
            # the resent data's tasks cancelled for lost dependencies).
            sends = self._sends[key] = self._sends.get(key, 0) + 1
            name = key if sends == 1 else f"{key}-{sends}"
            future = self._data[key] = self.client.scatter({name: obj}, broadcast=broadcast)[name]
        return future, size

    def map(
        self,
        fn: Callable,
        items: Iterable,
        progress: Callable[[Any], Any] | None = None,
    ) -> list:
        """``fn`` over ``items`` as tasks (``fn`` is pickled with every task: keep it
        small; tasks reading shared data go through :meth:`map_shared`)."""
        items = list(items)
        futures = self.client.map(fn, items, pure=False)
        return self._collect(futures, [f"task {k}" for k in range(len(items))], progress)

    def map_shared(
        self,
        fn: Callable,
        shared: Any,
        items: list,
        progress: Callable[[Any], Any] | None,
        labels: list[str],
    ) -> list:
        """``fn(shared, item)`` per item (:func:`mvreg.executor.map_shared`)."""
        if not items:
            return []
        ref, self.shared_bytes = self.share(shared)
        args = [self._inline_or_scattered(item) for item in items]
        self.task_bytes = max(
            task_size(fn, label, ref.key, arg.key if hasattr(arg, "key") else arg)
            for label, arg in zip(labels, args, strict=True)
        )
        futures = self.client.map(
            partial(run_task, fn), labels, [ref] * len(items), args, pure=False
        )
        return self._collect(futures, labels, progress)

    def _inline_or_scattered(self, item: Any):
        if len(pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)) <= SCATTER_ITEM_BYTES:
            return item
        return self.share(item, broadcast=False)[0]

    def _collect(self, futures: list, labels: list[str], progress) -> list:
        """Results in order; cancels every future on an error or an interrupt."""
        from distributed.client import FutureCancelledError

        out = []
        try:
            for future, label in zip(futures, labels, strict=True):
                try:
                    out.append(future.result())
                except MvregError:
                    raise
                except FutureCancelledError as e:
                    raise TaskError(label, f"cancelled by the scheduler: {LOST_DATA} ({e})") from e
                except Exception as e:  # noqa: BLE001 - a lost worker, a pickling error
                    raise TaskError(label, f"{type(e).__name__}: {e}") from e
                if progress is not None:
                    progress(out[-1])
        except BaseException:
            self.client.cancel(futures)
            raise
        return out

    def forget(self) -> None:
        """Release the data shared so far (the workers drop it and their caches)."""
        self._data.clear()

    def close(self) -> None:
        """Release the scattered data, close the client and a cluster started here."""
        self.forget()
        try:
            self.client.close()
        finally:
            if self.owns_cluster and self.cluster is not None:
                self.cluster.close()

    def __enter__(self) -> DaskExecutor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        where = "local cluster" if self.owns_cluster else self.client.scheduler.address
        return f"DaskExecutor(workers={self.workers}, {where})"


@contextlib.contextmanager
def open_executor(
    threads: int = 2, workers: int | None = None, scheduler: str | None = None
) -> Iterator[ThreadExecutor | DaskExecutor]:
    """The task executor of a run, closed on exit: ``scheduler`` (an address) connects
    to a running cluster, ``workers`` starts a local one of that many processes, neither
    gives in-process threads (``threads``)."""
    if scheduler is not None and workers is not None:
        raise ConfigError("give either workers (a local cluster) or scheduler, not both")
    if scheduler is None and workers is None:
        yield ThreadExecutor(threads)
        return
    ex = DaskExecutor.connect(scheduler) if scheduler else DaskExecutor.local(int(workers))
    with ex:
        yield ex
