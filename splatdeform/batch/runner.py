"""Run jobs on local worker processes (spawn context) or on a Dask distributed cluster.

Both call the same :func:`~splatdeform.batch.worker.process_scan`.

Local workers are long-lived processes, each fed one scan at a time over its own pipe, so the
runner always knows which scan a process is working on: a process that dies (killed, out of
memory, segfault) fails exactly its scan, and a scan over the per-scan time limit is stopped
(SIGTERM, which unwinds its cleanup handlers; SIGKILL after a grace period) and reported as
timed out. A stopped or dead worker is replaced; the other scans go on. The clock starts when
the scan is handed to a worker that has finished importing, so it measures the scan.

On Dask a running task is a thread that cannot be stopped, so with a time limit each scan runs
in a child process of the Dask worker (:func:`run_isolated`), stopped the same way.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import pickle
import select
import subprocess
import sys
import time
from collections import deque
from collections.abc import Callable
from multiprocessing.connection import wait as mp_wait
from pathlib import Path
from typing import Any

from .config import Job
from .worker import OUT_OF_MEMORY, _row, cap_memory, process_scan, warm_up, worker_init

Row = dict[str, Any]
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
GRACE_S = 3.0            # after SIGTERM, before SIGKILL
START_TIMEOUT_S = 300.0  # a worker process that cannot import in this time is broken
DIED = ("the worker process died while processing this scan (killed, out of memory or "
        "crashed)")


def timed_out(limit: float) -> str:
    return (f"timed out: still running after {limit:g} s (scan_timeout_s / --scan-timeout); "
            "the scan was stopped")


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


def _worker_main(conn: Any, fn: Callable[[Job], Row], parent: int) -> None:
    """A local worker process: import, say ready, then run one job per message until None."""
    import signal

    worker_init(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C: the batch process stops us
    warm_up()
    conn.send(("ready", None))
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        try:
            cap_memory(getattr(job, "memory_budget", None))
            row = fn(job)
        except MemoryError:
            row = _row(job, "failed", error=OUT_OF_MEMORY.format(
                mib=(job.memory_budget or 0) / 2**20))
        except Exception as exc:  # a task function that raises: fail its scan, keep serving
            row = _row(job, "failed", error=f"{type(exc).__name__}: {exc}")
        conn.send(("row", row))


class _Worker:
    """One worker process and the scan it is running."""

    def __init__(self, ctx: Any, fn: Callable[[Job], Row]) -> None:
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker_main, args=(child, fn, os.getpid()),
                                daemon=True)
        self.proc.start()
        child.close()
        self.started = time.monotonic()
        self.ready = False
        self.job: Job | None = None
        self.t0 = 0.0
        self.deadline: float | None = None

    def give(self, job: Job, timeout: float | None) -> None:
        self.conn.send(job)
        self.job, self.t0 = job, time.monotonic()
        self.deadline = None if timeout is None else self.t0 + timeout

    def stop(self, grace: float = GRACE_S) -> None:
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(grace)
            if self.proc.is_alive():
                self.proc.kill()
        self.proc.join()
        self.conn.close()


def run_local(jobs: list[Job], workers: int, on_done: Callable[[Row], None], *,
              fn: Callable[[Job], Row] = process_scan,
              timeout: float | None = None) -> list[Row]:
    """Worker-process execution with at most ``workers`` scans in flight (``fn``: the task, a
    picklable top-level function; ``timeout``: seconds per scan, None for no limit)."""
    from ..errors import ProcessingError
    from .extract import clean_stale_temps

    ctx = multiprocessing.get_context("spawn")
    pending = deque(jobs)
    rows: list[Row] = []
    saved = _thread_env(workers)
    pool: list[_Worker] = []
    failed_starts = 0

    def finish(job: Job, row: Row) -> None:
        rows.append(row)
        on_done(row)

    try:
        pool = [_Worker(ctx, fn) for _ in range(min(workers, len(pending)))]
        while pool:
            for w in pool:
                while w.ready and w.job is None and pending:
                    job = pending.popleft()
                    try:
                        w.give(job, timeout)
                    except (pickle.PicklingError, TypeError, AttributeError) as exc:
                        finish(job, _row(job, "failed", error=f"{type(exc).__name__}: {exc}"))
            now = time.monotonic()
            limits = [w.deadline for w in pool if w.deadline is not None] + \
                [w.started + START_TIMEOUT_S for w in pool if not w.ready]
            # at most an hour a wait: the OS wait calls overflow on huge timeouts (1e7 s)
            wait_s = min(3600.0, max(0.0, min(limits) - now)) if limits else None
            mp_wait([w.conn for w in pool] + [w.proc.sentinel for w in pool], wait_s)
            now = time.monotonic()
            for w in list(pool):
                gone = False
                try:
                    while w.conn.poll():
                        kind, payload = w.conn.recv()
                        if kind == "ready":
                            w.ready, failed_starts = True, 0
                        elif w.job is not None:
                            finish(w.job, payload)
                            w.job, w.deadline = None, None
                except (EOFError, OSError):
                    gone = True
                if w.job is not None and w.deadline is not None and now >= w.deadline:
                    job = w.job
                    w.stop()
                    finish(job, _row(job, "failed", seconds=now - w.t0,
                                     error=timed_out(timeout or 0)))
                    w.job, gone = None, True
                elif not w.ready and now >= w.started + START_TIMEOUT_S:
                    w.stop(grace=0.5)
                    gone = True
                elif gone or not w.proc.is_alive():
                    w.stop(grace=0.5)
                    gone = True
                if not gone:
                    continue
                if w.job is not None:
                    finish(w.job, _row(w.job, "failed", seconds=now - w.t0, error=DIED))
                    w.job = None
                elif not w.ready:
                    failed_starts += 1
                    if failed_starts >= 3:
                        raise ProcessingError("cannot start a batch worker process (it exited "
                                              f"with code {w.proc.exitcode} before it was ready)")
                clean_stale_temps()   # what a killed worker left behind
                pool.remove(w)
                busy = sum(x.job is not None for x in pool)
                if pending and len(pool) < min(workers, len(pending) + busy):
                    pool.append(_Worker(ctx, fn))
            if not pending:   # let idle workers go
                for w in [w for w in pool if w.job is None]:
                    if w.ready:
                        with contextlib.suppress(OSError):
                            w.conn.send(None)
                        w.proc.join(GRACE_S)
                    w.stop(grace=1.0)
                    pool.remove(w)
    finally:
        for w in pool:
            w.stop(grace=1.0)
        _restore_env(saved)
    return rows


def _child_env() -> dict[str, str]:
    """The environment for a scan's child process: it must import this very package."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    for var in THREAD_VARS:
        env.setdefault(var, "1")
    return env


def _read_line(fd: int, limit: float) -> bytes:
    """Bytes up to a newline from a pipe, or what arrived before ``limit`` (monotonic) / EOF."""
    data = b""
    while not data.endswith(b"\n"):
        left = limit - time.monotonic()
        if left <= 0 or not select.select([fd], [], [], left)[0]:
            break
        chunk = os.read(fd, 1)
        if not chunk:
            break
        data += chunk
    return data


def _communicate(proc: subprocess.Popen, data: bytes, timeout: float | None) -> bytes:
    """``proc.communicate(data)`` with a limit of ``timeout`` seconds, waited for an hour at a
    time (the OS wait calls overflow on a huge single timeout, e.g. 1e7 s)."""
    deadline = None if timeout is None else time.monotonic() + timeout
    first: bytes | None = data
    while True:
        left = None if deadline is None else deadline - time.monotonic()
        try:
            out, _ = proc.communicate(first, timeout=None if left is None else
                                      max(0.0, min(3600.0, left)))
            return out
        except subprocess.TimeoutExpired:
            first = None   # the input was sent; communicate() goes on where it stopped
            if deadline is not None and time.monotonic() >= deadline:
                raise


def run_isolated(job: Job) -> Row:
    """``process_scan(job)`` in a child process stopped after ``job.timeout_s`` seconds (the
    Dask path: a Dask task is a thread, which cannot be stopped). The clock starts once the
    child has imported. Never raises for the scan's problems."""
    from .extract import clean_stale_temps

    proc = subprocess.Popen([sys.executable, "-m", "splatdeform.batch.child"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=_child_env())
    assert proc.stdin is not None and proc.stdout is not None
    try:
        if _read_line(proc.stdout.fileno(), time.monotonic() + START_TIMEOUT_S) != b"ready\n":
            proc.kill()
            _, err = proc.communicate()
            last = (err.decode(errors="replace").strip().splitlines() or [""])[-1]
            return _row(job, "failed", error=f"the scan's child process did not start: {last}")
        t0 = time.monotonic()
        try:
            out = _communicate(proc, pickle.dumps(job), job.timeout_s)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.communicate(timeout=GRACE_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()
            clean_stale_temps()
            return _row(job, "failed", seconds=time.monotonic() - t0,
                        error=timed_out(job.timeout_s or 0))
        try:
            return pickle.loads(out)
        except Exception:
            return _row(job, "failed", seconds=time.monotonic() - t0,
                        error=f"{DIED} (exit code {proc.returncode})")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def dask_budget(client: Any) -> float | None:
    """Smallest per-thread memory limit over the cluster's workers (bytes), if any is set."""
    limits = []
    for w in client.scheduler_info().get("workers", {}).values():
        limit, threads = w.get("memory_limit") or 0, w.get("nthreads") or 1
        if limit:
            limits.append(limit / threads)
    return min(limits) if limits else None


def run_dask(jobs: list[Job], address: Any, on_done: Callable[[Row], None],
             budget: float | None = None, timeout: float | None = None) -> list[Row]:
    """Submit every job to the Dask cluster at ``address`` (a string or a Cluster object);
    with ``timeout`` each scan runs in a child process of its Dask worker (:func:`run_isolated`)."""
    from ..dask_client import dask_client

    rows: list[Row] = []
    with dask_client(address) as client:   # one line naming the extra when Dask is missing
        from distributed import as_completed

        if budget is None:
            budget = dask_budget(client)
        futures = {}
        for i, job in enumerate(jobs):
            job.memory_budget, job.timeout_s = budget, timeout
            task = run_isolated if job.timeout_s else process_scan
            fut = client.submit(task, job, key=f"splatdeform-{job.config_hash}-{i}",
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
    return rows
