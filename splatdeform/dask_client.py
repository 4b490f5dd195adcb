"""The one place that opens a Dask client: ``deform --scheduler`` / ``--workers`` (one scan split
over a cluster) and ``batch --scheduler`` / ``scheduler:`` (scans spread over a cluster).

Dask is an extra (``pip install 'splatdeform[dask]'``; ``make`` installs it): without it
:func:`require_dask` and :func:`dask_client` raise a one-line :class:`~splatdeform.errors.
InputError` naming the extra (exit 2). Batch's local ``--workers`` never come here (they are
multiprocessing workers) and need no Dask.

- **Timeout**: connecting to a scheduler address gives up after :data:`CONNECT_TIMEOUT_S`
  (20 s) with one line naming the address. Batch used 15 s and ``deform`` 20 s; the longer one
  is kept: a busy scheduler, or one reached across a slow network, answers late, while a wrong
  address is refused at once either way.
- **Signals**: Ctrl-C / SIGTERM are held while the client connects or a LocalCluster starts (a
  start cut short would leave worker processes nobody closes) and while they close, and act right
  after. When the block is stopped by one (KeyboardInterrupt, the CLI's SIGTERM exception), Dask's
  and asyncio's loggers in this process are silenced for good (the process is ending): the
  scheduler and client would report every transfer and task cut short, some only when they are
  garbage-collected.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from typing import Any

from .errors import InputError
from .interrupts import deferred_signals

#: what to install when Dask is missing
INSTALL_HINT = "pip install 'splatdeform[dask]'"
#: seconds a client waits for a scheduler address to answer
CONNECT_TIMEOUT_S = 20


def require_dask(what: str) -> None:
    """InputError (one line, exit 2) when ``dask.distributed`` cannot be imported; ``what``:
    the flag or key that asked for Dask (e.g. ``--workers``)."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise InputError(f"{what}: needs Dask, which is not installed; {INSTALL_HINT}") from None


@contextlib.contextmanager
def dask_client(scheduler: Any = None, workers: int | None = None, *,
                what: str | None = None) -> Iterator[Any]:
    """A ``distributed.Client`` on ``scheduler`` (an address like ``tcp://host:8786``, or a
    Cluster object), else on a new LocalCluster of ``workers`` single-threaded processes; closed
    (with the cluster it started) when the block ends. ``what``: the flag or key named in the
    error lines (default ``--scheduler``, or ``--workers`` for a local cluster)."""
    what = what or ("--scheduler" if scheduler else "--workers")
    require_dask(what)
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            with deferred_signals():
                client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"{what}: cannot reach the Dask scheduler at {scheduler}: "
                             f"{exc}") from exc
        with _closing(client.close):
            yield client
        return
    with deferred_signals():
        # the workers' own loggers at CRITICAL: a task's error reaches the client (one line);
        # a worker's heartbeat to a scheduler that is closing (a Ctrl-C, a busy machine) would
        # otherwise print a traceback of its own
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.CRITICAL)
        try:
            client = Client(cluster)
        except BaseException:
            cluster.close()
            raise
    with _closing(client.close, cluster.close):
        yield client


def silence_dask_logs() -> None:
    """Silence Dask's, asyncio's and tornado's loggers, every child logger included:
    distributed's sync() can log a NameError traceback through "tornado.application" when a
    signal cuts a call short, and distributed's logging config sets that child's own level
    (error), which a parent's level does not override."""
    prefixes = ("distributed", "asyncio", "tornado")
    names = [n for n in list(logging.root.manager.loggerDict) if n.startswith(prefixes)]
    for name in {*prefixes, *names}:
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)


@contextlib.contextmanager
def _closing(*close: Callable[[], Any]) -> Iterator[None]:
    """Run ``close`` functions after the block, with Ctrl-C / SIGTERM held; silence Dask's and
    asyncio's loggers when the block was stopped by a signal (see the module docstring)."""
    try:
        yield
    except BaseException as exc:
        if not isinstance(exc, Exception):
            silence_dask_logs()
        raise
    finally:
        with deferred_signals():
            for fn in close:
                fn()


__all__ = ["CONNECT_TIMEOUT_S", "INSTALL_HINT", "dask_client", "require_dask",
           "silence_dask_logs"]
