"""The one BLAS thread limiter: the fitter and the editor's per-frame products limit OpenBLAS
through it (an unlimited pool spins threads against other processes on a busy machine)."""

from __future__ import annotations

import functools
from contextlib import AbstractContextManager, nullcontext


def blas_threads(threads: int | None) -> AbstractContextManager:
    """Limit the BLAS thread pool to ``threads`` inside the block (None: leave it alone).

    The fitter makes many small BLAS calls; on a busy machine an unlimited OpenBLAS pool spins
    threads against other processes (measured 8x slower on 2 cores), so it limits itself; the
    editor's per-frame products run on one thread (10-30x slower oversubscribed, measured).
    """
    if threads is None:
        return nullcontext()
    return _controller().limit(limits=int(threads), user_api="blas")


@functools.cache
def _controller():
    """One threadpoolctl controller per process: creating one scans the loaded libraries
    (about a millisecond, as much as a whole small fit)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()
