"""The editor servers' foreground: Ctrl-C and SIGTERM set an event instead of raising, the
caller's ``finally`` shuts its server down, then the previous handlers come back."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


@contextlib.contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event that SIGINT / SIGTERM set while the block runs; the handlers before it are
    restored on the way out (after the block's own clean-up)."""
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def serve_until(stop: threading.Event, ready: threading.Event | None = None) -> None:
    """Tell ``ready`` (tests) the server is up, then block until ``stop`` is set."""
    if ready is not None:
        ready.set()
    while not stop.wait(0.25):
        pass
