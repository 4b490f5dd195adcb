"""``splatdeform batch BATCH.yaml``: one edit applied to many scans.

Batch config (paths relative to the batch file)::

    scans: scans/*.ply            # glob | list of globs/paths | folder (recursive) | .zip/.tar(.gz)
    edit: bend_bar.yaml           # an edit file or an inline mapping; its input/output are ignored
    overrides:                    # optional, applied in order to scans whose file name matches
      - match: "sphere*"
        edit: {regions: {handle: [{sphere: {center: [.5, .5, 1], radius: .3}}]}}   # deep-merged
    output_dir: out/batch         # must not be inside a scanned folder / matched by the glob
    render: {size: [256, 256], azimuth: 30, elevation: 20}   # optional thumbnails (per half)
    workers: 2                    # optional; default: the number of cores
    scheduler: tcp://host:8786    # optional; run on a Dask distributed cluster instead
    memory_per_worker_mb: 4000    # optional; default: half the RAM / workers running at once
    scan_timeout_s: 600           # optional; a scan still running after this is stopped and
                                  # reported failed (--scan-timeout SECONDS wins)

Per scan: ``output_dir/<stem>_deformed<ext>`` (same format and properties as the input),
``<stem>.png`` with ``render:``, and ``<stem>_deformed<ext>.json`` (the sidecar with the config
hash, written last). The run writes ``report.json``, ``report.csv`` and ``index.html``.
A rerun skips scans whose sidecar holds the same config hash (edit, overrides, render options,
input size/mtime, package version); ``--force`` redoes them. Exit code 1 when any scan failed.

Hostile inputs are reported, not fatal: a scan that is not a regular file (a FIFO or device
named ``*.ply``), the second entry of a duplicate archive member name, an archive that cannot be
read (or whose tar header is cut off, or whose zip entries overlap) each become a failed row
without being opened; a scan whose PLY header does not fit its size, or whose estimated memory
(:mod:`splatdeform.memory`, from the header) exceeds the budget, fails before it is loaded or
extracted (members are never extracted past the size the archive declares); a local worker runs
each scan under a memory cap (budget + 300 MiB), so a wrong estimate fails one scan.

The per-worker budget (``memory_per_worker_mb``; default :func:`splatdeform.memory.worker_budget`,
half the RAM shared by the workers running at once) is a cap, as ``deform --memory-budget``'s:
a scan file over it streams where ``deform`` would stream it (binary PLY, LAS/LAZ, a handle
edit) and is refused, with deform's line, where deform would refuse it. An archive member over
it is refused before extraction (it is not streamed: it would be extracted whole first). Archives
are listed and their members checked in one pass. The report is written on every exit, with
every name valid UTF-8 and escaped in ``index.html``.

Local execution uses worker processes started with "spawn" (OpenCL/GL state is never forked).
A Dask cluster runs the same task function; every worker must import ``splatdeform`` and see the
scan and output paths (a shared file system)::

    dask scheduler                                   # prints tcp://HOST:8786
    dask worker tcp://HOST:8786 --nworkers 2 --nthreads 1 --memory-limit 8GB   # on each node
    splatdeform batch batch.yaml --scheduler tcp://HOST:8786

With ``scan_timeout_s`` / ``--scan-timeout`` a local worker running a scan past the limit is
stopped (SIGTERM, then SIGKILL) and replaced; on Dask, where a running task is a thread that
cannot be stopped, each scan then runs in a child process of its Dask worker instead.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..lazy import lazy_exports

if TYPE_CHECKING:  # pragma: no cover
    from .config import Batch, BatchConfig, Job, load_batch

# The config models (pydantic) are imported on first use: the CLI registers this verb's parser
# for every run, and only ``batch`` itself reads a batch file.
__getattr__ = lazy_exports(__name__, {"Batch": "config", "BatchConfig": "config",
                                      "Job": "config", "load_batch": "config"})

__all__ = ["Batch", "BatchConfig", "Job", "load_batch", "run_batch", "register"]


def _strip_name(row: dict[str, Any]) -> str:
    """The error without a leading repeat of the scan's name."""
    err, name = row.get("error") or "", row["scan"]
    return err[len(name) + 2:] if err.startswith(name + ": ") else err


class _Progress:
    """A scan done: a tqdm bar on a terminal (failed scans written above it), else one line per
    scan on stdout, ``[n/total] scan: status ...``, written by tqdm too (LineBar)."""

    def __init__(self, total: int, quiet: bool) -> None:
        self.total, self.quiet, self.n = total, quiet, 0
        self.bar = None
        self.msg = ""
        self.terminal = not quiet and sys.stderr.isatty()
        if quiet:
            return
        from ..progress import LineBar, tqdm

        if self.terminal:
            self.bar = tqdm(total=total, unit="scan", dynamic_ncols=True)
        else:
            self.bar = LineBar(total=total, mininterval=0, line=self._line,
                               sink=lambda line: print(line, flush=True))

    def _line(self, bar: dict[str, Any]) -> str:
        return f"[{bar['n']}/{self.total}] {self.msg}"

    def __call__(self, row: dict[str, Any]) -> None:
        from .report import printable

        self.n += 1
        msg = f"{printable(row['scan'])}: {row['status']}"
        if row["status"] == "failed" or row.get("error"):
            msg += f": {printable(_strip_name(row))}"
        elif row.get("seconds") is not None:
            msg += f" ({row['seconds']:.1f} s)"
        self.msg = msg
        if self.bar is not None:
            self.bar.update(1)
            if row["status"] == "failed" and self.terminal:
                self.bar.write(msg)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def run_batch(path: str | Path, *, workers: int | None = None, scheduler: Any = None,
              force: bool = False, quiet: bool = False,
              scan_timeout: float | None = None) -> dict[str, Any]:
    """Run a batch file; returns the report summary (``rows``, ``counts``, ``exit_code``).

    ``scheduler`` may be an address or a Dask Cluster/Client object (tests).
    ``scan_timeout``: seconds per scan, wins over the config's ``scan_timeout_s``."""
    from ..io.atomic import remove_stale_temps
    from ..memory import worker_budget
    from .config import load_batch
    from .extract import clean_stale_temps
    from .report import write_reports
    from .runner import run_dask, run_local
    from .worker import _row, read_sidecar

    t0 = time.perf_counter()
    if scan_timeout is not None:
        scan_timeout = parse_timeout(scan_timeout, "--scan-timeout")
    batch = load_batch(path)
    scheduler = scheduler or batch.scheduler
    timeout = scan_timeout if scan_timeout is not None else batch.scan_timeout_s
    if workers is not None and workers < 1:
        from ..errors import InputError

        raise InputError(f"--workers: expected a positive number, got {workers}")
    workers = workers or batch.workers or os.cpu_count() or 1
    batch.output_dir.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(batch.output_dir, any_output=True)   # a killed run's outputs in writing
    clean_stale_temps()   # archive members of killed runs / workers on this machine

    rows: dict[int, dict[str, Any]] = {}
    todo: list[Job] = []
    problems: list[dict[str, Any]] = []
    budget = batch.memory_per_worker_mb * 2**20 if batch.memory_per_worker_mb else None
    if budget is None and not scheduler:
        budget = worker_budget(min(workers, len(batch.jobs)))
    for i, job in enumerate(batch.jobs):
        problem = job.problem or _over_budget(job, budget)
        if problem is not None:   # never opened: a FIFO, a duplicate member, over budget ...
            rows[i] = _row(job, "failed", seconds=0.0, error=problem)
            problems.append(rows[i])
            continue
        side = None if force else read_sidecar(job)
        if side is not None:
            rows[i] = {**side.get("row", {}), "scan": job.scan.name, "status": "skipped"}
        else:
            todo.append(job)
    index = {id(job): i for i, job in enumerate(batch.jobs)}
    progress = _Progress(len(todo) + len(problems), quiet)
    skipped = len(rows) - len(problems)
    if not quiet and skipped:
        print(f"skipping {skipped} scan(s) already done with this config (--force redoes "
              "them)", flush=True)
    stopped = "not run: the batch was stopped before this scan finished"
    try:
        for row in problems:
            progress(row)
        if todo:
            if scheduler:
                done = run_dask(todo, scheduler, progress, budget, timeout)
            else:
                for job in todo:
                    job.memory_budget = budget
                done = run_local(todo, workers, progress, timeout=timeout)
            by_name = {job.scan.name: index[id(job)] for job in todo}
            for row in done:
                rows[by_name[row["scan"]]] = row
    except BaseException as exc:   # the report is written on every exit, then the error goes on
        stopped = f"not run: the batch stopped ({type(exc).__name__}: {exc})"
        raise
    finally:
        progress.close()
        clean_stale_temps()
        for job in todo:   # scans a stopped run never finished are rows too
            rows.setdefault(index[id(job)], _row(job, "failed", error=stopped))
        ordered = [rows[i] for i in sorted(rows)]
        counts = {s: sum(r["status"] == s for r in ordered) for s in ("ok", "failed", "skipped")}
        summary = {"batch": str(batch.source), "output_dir": str(batch.output_dir),
                   "workers": None if scheduler else workers,
                   "scheduler": scheduler if isinstance(scheduler, str) else
                   (None if scheduler is None else type(scheduler).__name__),
                   "scan_timeout_s": timeout, "memory_per_worker_mb":
                   None if budget is None else round(budget / 2**20),
                   "seconds": time.perf_counter() - t0, "counts": counts,
                   "config": batch.config}
        write_reports(batch.output_dir, ordered, summary)
    summary["rows"] = ordered
    summary["exit_code"] = 1 if counts["failed"] else 0
    return summary


def _over_budget(job: Job, budget: float | None) -> str | None:
    """An archive member whose header-based estimate exceeds the per-worker budget is refused
    before it is extracted or sent to a worker (members are not streamed; a scan file's
    stream-or-not is the worker's pre-flight, :func:`splatdeform.edit.plan.plan_edit`)."""
    from ..memory import choose

    need = job.scan.need
    if budget is None or need is None:
        return None
    if choose(need, int(budget), streamable=False, name=job.scan.name).mode != "refuse":
        return None
    return (f"{job.scan.name}: needs about {need / 2**20:.0f} MiB (estimated from its header "
            f"and size), more than the {budget / 2**20:.0f} MiB per worker; use fewer workers "
            "or set memory_per_worker_mb")


def parse_timeout(value: Any, what: str) -> float:
    """Seconds > 0 and finite (at most ``MAX_TIMEOUT_S``); InputError naming ``what``."""
    from ..errors import InputError
    from .config import MAX_TIMEOUT_S

    try:
        seconds = float(value)
        if not 0 < seconds <= MAX_TIMEOUT_S:   # also false for NaN
            raise ValueError
    except (TypeError, ValueError):
        raise InputError(f"{what}: expected a number of seconds > 0 and at most "
                         f"{MAX_TIMEOUT_S:g}, got {value!r}") from None
    return seconds


def _timeout_argument(value: str) -> float:
    """argparse type of ``--scan-timeout``: its error says what was expected (argparse itself
    would print ``invalid <lambda> value``)."""
    from ..errors import InputError

    try:
        return parse_timeout(value, "--scan-timeout")
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[1]) from None


def cmd_batch(args: argparse.Namespace) -> int:
    from .report import printable

    summary = run_batch(args.config, workers=args.workers, scheduler=args.scheduler,
                        force=args.force, quiet=args.quiet, scan_timeout=args.scan_timeout)
    c = summary["counts"]
    line = (f"{len(summary['rows'])} scans: {c['ok']} ok, {c['failed']} failed, "
            f"{c['skipped']} skipped in {summary['seconds']:.1f} s; report "
            f"{Path(summary['output_dir']) / 'index.html'}")
    if c["failed"] and args.quiet:   # otherwise the progress lines showed them
        for row in summary["rows"]:
            if row["status"] == "failed":
                print(f"splatdeform: failed: {printable(row['scan'])}: "
                      f"{printable(_strip_name(row))}", file=sys.stderr)
    if not args.quiet or c["failed"]:
        print(line, file=sys.stderr if args.quiet else sys.stdout)
    return summary["exit_code"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("batch", help="apply one edit to many scans (local workers or Dask)")
    p.add_argument("config", help="batch YAML file")
    p.add_argument("--workers", type=int, help="local worker processes (default: cores)")
    p.add_argument("--scheduler", help="Dask scheduler address, e.g. tcp://host:8786")
    p.add_argument("--scan-timeout", type=_timeout_argument,
                   metavar="SECONDS", help="stop a scan after this many seconds and report it "
                   "failed (wins over scan_timeout_s in the batch file)")
    p.add_argument("--force", action="store_true", help="redo scans already done")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_batch)
