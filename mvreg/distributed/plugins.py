"""Worker plugins of the local cluster (imports ``distributed``: loaded only with one)."""

from __future__ import annotations

import signal
import threading

from distributed import WorkerPlugin


class IgnoreInterrupt(WorkerPlugin):
    """The worker processes of a local cluster ignore SIGINT. Ctrl-C in a terminal reaches
    the whole process group; the client then cancels the tasks and closes the cluster,
    instead of every worker dying with a traceback. Applies once a worker has started
    (also to a worker a nanny restarts): a Ctrl-C in the first seconds of the cluster's
    start, while the worker processes import, still shows their tracebacks (the run
    exits 130 all the same)."""

    def setup(self, worker) -> None:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)
