"""What every stage of a run shares: configuration, timing, progress, recording, executor.

A stage gets the :class:`Run` and the data it needs, and returns its own output; it
reports progress through ``run.progress`` and its wall time through ``run.timed(name)``
(the time since the previous call), and logs to ``run.recorder`` (a no-op by default).

Two executors: ``run.executor`` runs the per-scan and per-pair tasks of preprocessing and
pairwise alignment -- in-process threads by default, a Dask cluster with ``workers`` or
``scheduler`` (:mod:`mvreg.distributed`, started on first use and closed with the run);
``run.local`` is in-process threads (``threads``) for the work that stays on the client
(the rotation search, tracks, refinement, verification). A run is a context manager.
"""

from __future__ import annotations

import contextlib
import time

from mvreg.config import RegisterConfig
from mvreg.executor import Executor, ThreadExecutor, make_executor, single_threaded_blas
from mvreg.viz import NullRecorder


class NoProgress:
    """The progress interface (the CLI passes rich progress bars with the same methods)."""

    def stage(self, name: str, total: int | None = None) -> None: ...
    def advance(self, n: int = 1) -> None: ...
    def done(self) -> None: ...


class Run:
    """One run's shared state. ``timings`` maps stage names to seconds, plus ``total``."""

    def __init__(
        self,
        cfg: RegisterConfig,
        recorder=None,
        progress=None,
        executor: Executor | int | None = None,
    ):
        self.cfg = cfg
        self.recorder = recorder if recorder is not None else NullRecorder()
        self.progress = progress if progress is not None else NoProgress()
        self.local = ThreadExecutor(cfg.threads)
        self._executor = None if executor is None else make_executor(executor)
        self._exit = contextlib.ExitStack()
        self.timings: dict = {}
        self._start = self._clock = time.perf_counter()
        self._solver_step = 0

    @property
    def executor(self) -> Executor:
        """The task executor (module docstring); a cluster is started on first use."""
        if self._executor is None:
            from mvreg.distributed import open_executor

            cfg, start = self.cfg, time.perf_counter()
            self._executor = self._exit.enter_context(
                open_executor(cfg.threads, cfg.workers, cfg.scheduler)
            )
            if cfg.workers is not None or cfg.scheduler is not None:
                # the cluster's start is its own timing, not part of the stage that needs it
                self.timings["start_cluster"] = time.perf_counter() - start
                self._clock += self.timings["start_cluster"]
        return self._executor

    def close(self) -> None:
        """Close the executor opened by this run (cancelled tasks, cluster shut down)."""
        self._exit.close()

    def __enter__(self) -> Run:
        # BLAS on one thread for the whole run: OpenBLAS splits a product differently for
        # another thread count, the sums round differently, and on a long chain of
        # decisions that changes what is registered (60 LiDAR stations: 47 scans with one
        # thread, 39 with two). The stages parallelize over scans and pairs instead.
        self._exit.enter_context(single_threaded_blas())
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def timed(self, name: str) -> None:
        """Add the time since the previous call (or the start) to ``name`` (a stage run
        again, as the global stage after verification drops scans, sums its runs)."""
        now = time.perf_counter()
        self.timings[name] = self.timings.get(name, 0.0) + now - self._clock
        self._clock = now

    def finish(self) -> None:
        self.timings["total"] = time.perf_counter() - self._start

    def on_iteration(self, record) -> None:
        """Solver callback: one point per iteration on the recording's solver timeline."""
        self._solver_step += 1
        self.recorder.log_solver_iteration(
            self._solver_step,
            record.objective,
            record.primal_residual,
            record.dual_residual,
            record.rho,
        )
