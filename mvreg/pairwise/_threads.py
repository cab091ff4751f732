"""BLAS thread limit for the many small matrix products of this package."""

from __future__ import annotations

import contextlib


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
