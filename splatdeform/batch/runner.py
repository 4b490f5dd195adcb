"""Run jobs on local worker processes (spawn context) or on a Dask distributed cluster.

Both call the same :func:`~splatdeform.batch.worker.process_scan`. A worker process that dies
(killed, out of memory, segfault) marks only its scan failed: after a broken pool the scans
that were in flight are retried one at a time in a fresh pool, so the culprit is found exactly.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from .config import Job
from .worker import _row, process_scan, worker_init

Row = dict[str, Any]
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _thread_env(workers: int) -> dict[str, str | None]:
    """One BLAS/OpenMP thread per worker process unless the user set them: the incremental QR
    is level-2 BLAS on small blocks, where threads cost more than they give (1.3-1.7 s vs
    0.8 s fit for a 200k-point bar on 2 cores); parallelism comes from the processes."""
    share = "1"
    saved = {}
    for var in THREAD_VARS:
        saved[var] = os.environ.get(var)
        os.environ.setdefault(var, share)
    return saved


def _restore_env(saved: dict[str, str | None]) -> None:
    for var, value in saved.items():
        if value is None:
            os.environ.pop(var, None)
        else:
            os.environ[var] = value


def run_local(jobs: list[Job], workers: int, on_done: Callable[[Row], None], *,
              fn: Callable[[Job], Row] = process_scan) -> list[Row]:
    """Process-pool execution with at most ``workers`` scans in flight (``fn``: the task,
    a picklable top-level function)."""
    ctx = multiprocessing.get_context("spawn")
    pending = list(jobs)
    suspects: list[Job] = []     # in flight when a pool broke: retried alone
    rows: list[Row] = []
    saved = _thread_env(workers)
    try:
        while pending or suspects:
            pool = ProcessPoolExecutor(max_workers=min(workers, len(pending) + len(suspects)),
                                       mp_context=ctx, initializer=worker_init,
                                       initargs=(os.getpid(),))
            running: dict[Any, Job] = {}
            broken = False
            try:
                while (pending or suspects or running) and not broken:
                    limit = 1 if suspects else workers
                    while len(running) < limit and (suspects or pending):
                        job = suspects.pop(0) if suspects else pending.pop(0)
                        running[pool.submit(fn, job)] = job
                    done, _ = wait(running, return_when=FIRST_COMPLETED)
                    for fut in done:
                        job = running.pop(fut)
                        try:
                            row = fut.result()
                        except BrokenProcessPool:
                            broken = True
                            if limit == 1:   # alone in the pool: this scan killed its worker
                                row = _row(job, "failed", error="the worker process died while "
                                           "processing this scan (killed, out of memory or "
                                           "crashed)")
                            else:
                                suspects.append(job)
                                continue
                        except Exception as exc:  # pickling problems and the like
                            row = _row(job, "failed", error=f"{type(exc).__name__}: {exc}")
                        rows.append(row)
                        on_done(row)
                if broken:
                    suspects.extend(running.values())
                    running.clear()
            finally:
                pool.shutdown(wait=not broken, cancel_futures=True)
    finally:
        _restore_env(saved)
    return rows


def dask_budget(client: Any) -> float | None:
    """Smallest per-thread memory limit over the cluster's workers (bytes), if any is set."""
    limits = []
    for w in client.scheduler_info().get("workers", {}).values():
        limit, threads = w.get("memory_limit") or 0, w.get("nthreads") or 1
        if limit:
            limits.append(limit / threads)
    return min(limits) if limits else None


def run_dask(jobs: list[Job], address: Any, on_done: Callable[[Row], None],
             budget: float | None = None) -> list[Row]:
    """Submit every job to the Dask cluster at ``address`` (a string or a Cluster object)."""
    try:
        from distributed import Client, as_completed
    except ImportError as exc:  # pragma: no cover
        from ..errors import InputError

        raise InputError("--scheduler needs dask.distributed: pip install 'dask[distributed]'"
                         ) from exc
    from ..errors import InputError

    try:
        client = Client(address, timeout="15s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(f"cannot connect to the Dask scheduler {address}: {exc}") from exc
    rows: list[Row] = []
    try:
        if budget is None:
            budget = dask_budget(client)
        futures = {}
        for i, job in enumerate(jobs):
            job.memory_budget = budget
            fut = client.submit(process_scan, job, key=f"splatdeform-{job.config_hash}-{i}",
                                pure=False, retries=0)
            futures[fut] = job
        for fut in as_completed(futures):
            job = futures[fut]
            try:
                row = fut.result()
            except Exception as exc:   # KilledWorker and the like
                row = _row(job, "failed", error=f"Dask worker failed: {type(exc).__name__}: "
                                                f"{' '.join(str(exc).split())[:300]}")
            rows.append(row)
            on_done(row)
    finally:
        client.close()
    return rows
