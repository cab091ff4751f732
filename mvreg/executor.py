"""Where per-scan and per-pair work runs: the executor seam.

A stage hands its independent tasks to an :class:`Executor` and gets the results back
in the order of the inputs, so the result never depends on how many workers ran them or
in which order they finished. The default runs in-process on threads (NumPy, SciPy's
KD-trees and Open3D release the GIL); a distributed executor plugs in here by
implementing the same two methods (:class:`mvreg.distributed.DaskExecutor`).

Tasks that all read the same large data (the run's scans) go through :func:`map_shared`:
``fn(shared, item)`` with a module-level ``fn``. In-process that is a plain call; a
distributed executor sends ``shared`` to each worker once, by key, so that a task carries
only ``fn``, its item and that key. Any error a task raises that is not already an
:class:`~mvreg.errors.MvregError` comes back as a :class:`~mvreg.errors.TaskError` naming
the task (the scan or the pair), whichever executor ran it.

Example (a new executor)::

    class SerialExecutor:
        workers = 1

        def map(self, fn, items, progress=None):
            out = []
            for item in items:
                out.append(fn(item))
                if progress is not None:
                    progress(out[-1])
            return out
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Protocol, TypeVar, runtime_checkable

from mvreg.errors import MvregError, TaskError

T = TypeVar("T")
R = TypeVar("R")


def single_threaded_blas():
    """Context manager running BLAS on one thread.

    OpenBLAS threads on small matrices are much slower than one thread (they busy-wait,
    badly so on a loaded machine), and results no longer depend on the thread count.
    Uses threadpoolctl when installed; otherwise a no-op. The limit is process-wide: enter
    it before starting worker threads.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional dependency
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


@runtime_checkable
class Executor(Protocol):
    """Runs independent tasks; ``map`` returns results in the order of ``items``."""

    workers: int

    def map(
        self,
        fn: Callable[[T], R],
        items: Iterable[T],
        progress: Callable[[R], Any] | None = None,
    ) -> list[R]: ...


class ThreadExecutor:
    """In-process threads (the default). ``workers=1`` runs in the calling thread.

    ``progress`` is called from the calling thread after each result, in input order.
    BLAS is limited to one thread while tasks run (see :func:`single_threaded_blas`).
    """

    def __init__(self, workers: int = 2):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = int(workers)

    def map(
        self,
        fn: Callable[[T], R],
        items: Iterable[T],
        progress: Callable[[R], Any] | None = None,
    ) -> list[R]:
        items = list(items)
        out: list[R] = []
        with single_threaded_blas():
            if self.workers == 1 or len(items) <= 1:
                for item in items:
                    out.append(fn(item))
                    if progress is not None:
                        progress(out[-1])
                return out
            with ThreadPoolExecutor(max_workers=self.workers) as pool:
                for r in pool.map(fn, items):
                    out.append(r)
                    if progress is not None:
                        progress(r)
        return out

    def __repr__(self) -> str:
        return f"ThreadExecutor(workers={self.workers})"


def make_executor(workers: int | Executor | None = None) -> Executor:
    """An executor from a worker count (threads), or the given executor itself."""
    if workers is None:
        return ThreadExecutor(2)
    if isinstance(workers, int):
        return ThreadExecutor(workers)
    return workers


def run_task(fn: Callable[[Any, T], R], label: str, shared: Any, item: T) -> R:
    """``fn(shared, item)``; an error that is not an MvregError becomes a TaskError
    naming the task by ``label`` (e.g. ``"pair scan_001.ply, scan_004.ply"``)."""
    try:
        return fn(shared, item)
    except MvregError:
        raise
    except Exception as e:  # noqa: BLE001 - re-raised, typed and named
        raise TaskError(label, f"{type(e).__name__}: {e}") from e


def map_shared(
    executor: Executor,
    fn: Callable[[Any, T], R],
    shared: Any,
    items: Iterable[T],
    progress: Callable[[R], Any] | None = None,
    labels: Iterable[str] | None = None,
) -> list[R]:
    """``[fn(shared, item) for item in items]`` on ``executor``, in the order of ``items``.

    ``shared`` is what every task reads (scans, an aligner): an executor with its own
    ``map_shared`` (a distributed one) sends it to each worker once and tasks refer to it
    by key; ``fn`` should then be a module-level function, so that a task pickles small.
    ``labels`` name the tasks in errors (:func:`run_task`; default ``"task k"``).
    """
    items = list(items)
    labels = [f"task {k}" for k in range(len(items))] if labels is None else list(labels)
    own = getattr(executor, "map_shared", None)
    if own is not None:
        return own(fn, shared, items, progress, labels)
    tasks = list(zip(labels, items, strict=True))
    return executor.map(lambda t: run_task(fn, t[0], shared, t[1]), tasks, progress)
