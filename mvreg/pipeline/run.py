"""What every stage of a run shares: configuration, timing, progress, recording, executor.

A stage gets the :class:`Run` and the data it needs, and returns its own output; it
reports progress through ``run.progress`` and its wall time through ``run.timed(name)``
(the time since the previous call), and logs to ``run.recorder`` (a no-op by default).
"""

from __future__ import annotations

import time

from mvreg.config import RegisterConfig
from mvreg.executor import Executor, make_executor
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
        self.executor = make_executor(cfg.workers if executor is None else executor)
        self.timings: dict = {}
        self._start = self._clock = time.perf_counter()
        self._solver_step = 0

    def timed(self, name: str) -> None:
        """Record the time since the previous call (or the start) under ``name``."""
        now = time.perf_counter()
        self.timings[name] = now - self._clock
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
