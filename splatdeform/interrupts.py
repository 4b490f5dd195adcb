"""Ctrl-C and SIGTERM around native work that runs on helper threads.

A Python signal handler that raises (``KeyboardInterrupt``; the CLI's ``Terminated`` for SIGTERM)
interrupts the main thread wherever it is. When that is a thread join inside a library call, the
call's daemon threads keep running on its native buffers while the process unwinds and finalizes,
and finalization frees those buffers under them: SciPy's ``cKDTree.query(..., workers=-1)`` then
crashes the process (exit -11 instead of 143). :func:`deferred_signals` holds SIGINT/SIGTERM for
the length of such a call and delivers them, to the handlers that were in place, when it returns;
:func:`knn_query` is the threaded kd-tree query wrapped that way.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from typing import Any

HELD = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def deferred_signals() -> Iterator[None]:
    """Hold SIGINT/SIGTERM that arrive inside the block; re-raise them (once each, in arrival
    order) when it ends, so the handlers in place before the block act on them. Outside the main
    thread (where Python cannot install handlers) the block runs unchanged. Nests."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous: dict[int, Any] = {}

    def hold(signum: int, _frame: object) -> None:
        held.append(signum)

    try:
        for sig in HELD:
            previous[sig] = signal.signal(sig, hold)
        yield
    finally:
        for sig, handler in previous.items():
            # None: a handler installed outside Python; the default is the closest we can restore
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        for sig in dict.fromkeys(held):
            signal.raise_signal(sig)


def knn_query(tree: Any, points: Any, **kwargs: Any) -> Any:
    """``tree.query(points, workers=-1, **kwargs)`` (a SciPy ``cKDTree``) with SIGINT/SIGTERM
    held until its threads have finished (see the module docstring)."""
    with deferred_signals():
        return tree.query(points, workers=-1, **kwargs)


__all__ = ["deferred_signals", "knn_query"]
