"""The OpenCL kernels' first build on a machine: one note while it is slow, and the warm-up
``make setup`` runs.

PoCL compiles a kernel with LLVM the first time (seconds: 1.9 s for the basis kernel on two
loaded cores, 5.2 s measured on a fresh machine) and keeps the binary in its cache
(``$POCL_CACHE_DIR``, else ``$XDG_CACHE_HOME/pocl``, else ``~/.cache/pocl``); later processes
load it in about 0.1 s. pyopencl leaves PoCL's builds to that cache and keeps binaries of other
drivers in its own (``~/.cache/pyopencl``). A build still running after :data:`NOTE_AFTER_S` is
a cold cache: the sink the CLI installs (:func:`set_note_sink`) says so once per process. The
library alone says nothing (no sink). ``SPLATDEFORM_NOTE_AFTER_S`` sets the threshold (0: say it
at the first build of the process, cached or not).

``python -m splatdeform.basis.kernel_warm`` (``make setup``) builds the kernels a deform uses on
this machine's default device ahead (nothing, and exit 0, without one).
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

#: seconds a build may take before it is said to be a first (uncached) build
NOTE_AFTER_S = 1.0

_SINK: list[Callable[[str], None]] = []
_SAID = threading.Event()


def set_note_sink(sink: Callable[[str], None] | None) -> None:
    """Where the one note goes (the CLI: a stderr line); None: nowhere."""
    _SINK[:] = [] if sink is None else [sink]


def cache_place(platform: str) -> str:
    """Where the driver of ``platform`` (its OpenCL platform name) caches built kernels."""
    if "Portable Computing Language" in platform:
        if os.environ.get("POCL_CACHE_DIR"):
            return os.environ["POCL_CACHE_DIR"]
        base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
        return str(Path(base) / "pocl")
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return f"{Path(base) / 'pyopencl'} or the driver's own cache"


@contextlib.contextmanager
def noting_slow_build(what: str, platform: str, after: float | None = None) -> Iterator[None]:
    """Run a kernel build; if it is still running after ``after`` seconds (default
    :data:`NOTE_AFTER_S`; 0: at once) and nothing was said yet, give the sink one line."""
    if after is None:   # the environment may set it (tests: 0, the note at every first build)
        with contextlib.suppress(ValueError):
            after = float(os.environ.get("SPLATDEFORM_NOTE_AFTER_S", NOTE_AFTER_S))
    wait = NOTE_AFTER_S if after is None else after

    def say() -> None:
        if _SINK and not _SAID.is_set():
            _SAID.set()
            _SINK[0](f"compiling the OpenCL {what} kernel for this device (the first use on "
                     f"this machine; later runs load it from the cache in "
                     f"{cache_place(platform)})")

    if wait <= 0:
        say()
        yield
        return
    timer = threading.Timer(wait, say)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
