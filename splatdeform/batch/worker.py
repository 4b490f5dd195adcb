"""The per-scan task: runs in a local worker process or on a Dask worker.

``process_scan(job) -> row`` never raises for a problem with the scan itself: it returns a row
with status "failed" and a one-line message, so one broken scan cannot stop the others.
Outputs are written atomically: the model, then the thumbnails (the whole model, then the
changed part's close-up: :mod:`.thumbnails`), then the sidecar
``<output>.json`` holding the config hash. Only a sidecar with the right hash makes a rerun skip
the scan, so a run killed at any moment is redone where it was incomplete.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
import traceback
from pathlib import Path
from typing import Any

from ..errors import error_line
from ..memory import CAP_SLACK_BYTES  # the cap's slack (memory's budget figures)
from .config import Job

#: longest error a report row keeps (errors.error_line's limit)
ROW_CHARS = 500
#: a scan's sidecar is one report row (a few hundred bytes): anything bigger is not ours
MAX_SIDECAR_BYTES = 1 << 20


def read_sidecar(job: Job) -> dict[str, Any] | None:
    """The sidecar when it matches this job (same hash, model and thumbnail present); read
    through the one opener (a regular file of at most MAX_SIDECAR_BYTES), else None (redo)."""
    from ..errors import SplatdeformError
    from ..io.regular import read_regular

    try:
        data = json.loads(read_regular(job.sidecar, max_bytes=MAX_SIDECAR_BYTES,
                                       what="batch sidecar").decode("utf-8"))
    except (OSError, ValueError, SplatdeformError, RecursionError):
        return None
    if not isinstance(data, dict) or data.get("config_hash") != job.config_hash:
        return None
    if not Path(job.output).is_file() or (job.png and not Path(job.png).is_file()):
        return None
    row = data.get("row")
    shown = row.get("closeup") if isinstance(row, dict) else None
    if shown and (shown != job.closeup or not Path(shown).is_file()):
        return None   # the close-up the report shows is gone: redo the scan
    return data


def _row(job: Job, status: str, **extra: Any) -> dict[str, Any]:
    return {"scan": job.scan.name, "status": status, "output": job.output, "png": job.png,
            "closeup": None, "points": None, "centers": None, "residual": None,
            "constraint_error": None, "constraint_error_rel": None, "converged": None,
            "timings": {}, "seconds": None, "error": "", **extra}


def process_scan(job: Job) -> dict[str, Any]:
    """Deform one scan; returns its report row (never raises for scan problems)."""
    from splatdeform.edit.config import RenderCfg, parse_edit
    from splatdeform.edit.plan import plan_edit
    from splatdeform.edit.run import run_edit

    from ..errors import SplatdeformError
    from ..io import atomic_write
    from ..memory import MIN_BUDGET
    from ..rbf.defaults import DEFAULT_MAX_CENTERS
    from .extract import clean_stale_temps, materialize
    from .probe import check, estimate_memory, probe

    t0 = time.perf_counter()
    if job.problem is not None:
        return _row(job, "failed", seconds=0.0, error=job.problem)
    clean_stale_temps()   # on a Dask node this is the only place that sees its temp folder
    warning = ""
    closeup: str | None = None
    local: Path | None = None

    def vet(head: bytes, size: int) -> None:
        """Before loading (and before extracting a member): header vs size; an archive member
        (never streamed: it would be extracted whole first) or a budget too small to stream
        in must fit the budget. A file's stream-or-not is the pre-flight's (deform's rule)."""
        p = probe(job.scan.name, head, size, suffix=job.scan.extension)
        fit = job.edit.get("fit") if isinstance(job.edit.get("fit"), dict) else {}
        centers = fit.get("max_centers", DEFAULT_MAX_CENTERS)
        centers = centers if isinstance(centers, int) else DEFAULT_MAX_CENTERS
        check(job.scan.name, p)   # the header against the size
        if job.scan.member is not None or scan_budget(job)[0] < MIN_BUDGET:
            budget_check(job, estimate_memory(p, centers), p)

    try:
        with materialize(job.scan, vet) as local:
            cfg = parse_edit({**job.edit, "input": str(local), "output": job.output},
                             job.scan.name, "edit")
            result = run_edit(plan_edit(cfg, job.base_dir, output=job.output,
                                        stream=scan_options(job, cfg)))
            if job.png and job.render:
                try:
                    from .thumbnails import render_thumbnails

                    r = job.render
                    cfg.render = RenderCfg(output=job.png, size=[2 * r["size"][0], r["size"][1]],
                                           azimuth=r["azimuth"], elevation=r["elevation"],
                                           fov=r["fov"], zoom=r.get("zoom", 1.0), up=r.get("up"),
                                           roll=r.get("roll", 0.0), camera=r.get("camera"),
                                           color=r.get("color"))
                    closeup = render_thumbnails(   # atomically; the close-up when it adds
                        result, cfg, job.png, job.closeup, input_path=local,
                        budget=int(job.memory_budget) if job.memory_budget else None)
                except Exception as exc:  # a thumbnail must not fail the scan
                    warning = f"thumbnail not rendered: {error_line(exc, limit=ROW_CHARS)}"
    except SplatdeformError as exc:
        msg = error_line(exc, limit=ROW_CHARS)
        if local is not None and job.scan.member is not None:   # name the member, not the temp
            msg = msg.replace(str(local), job.scan.name)
        return _row(job, "failed", seconds=time.perf_counter() - t0, error=msg)
    except MemoryError:
        return _row(job, "failed", seconds=time.perf_counter() - t0,
                    error=OUT_OF_MEMORY.format(mib=(job.memory_budget or 0) / 2**20))
    except Exception as exc:  # an unexpected bug: keep the batch going, say where
        where = traceback.extract_tb(exc.__traceback__)[-1]
        return _row(job, "failed", seconds=time.perf_counter() - t0,
                    error=f"{type(exc).__name__}: {error_line(exc, limit=ROW_CHARS)} "
                          f"({Path(where.filename).name}:{where.lineno})")
    s = result.stats
    row = _row(job, "ok", points=s["points"], constraints=s["constraints"], kept=s["kept"],
               method=s["method"], centers=s["centers"], residual=s["residual"],
               constraint_error=s["constraint_error"],
               constraint_error_rel=s["constraint_error_rel"], converged=s["converged"],
               timings={k: round(v, 4) for k, v in result.timings.items()},
               seconds=time.perf_counter() - t0, error=warning,
               png=job.png if (job.png and not warning) else None,
               closeup=None if warning else closeup)
    sidecar = {"config_hash": job.config_hash, "scan": job.scan.name, "row": row}
    with atomic_write(job.sidecar) as f:
        f.write(json.dumps(sidecar, indent=1).encode())
    return row


OUT_OF_MEMORY = ("out of memory: the scan outgrew its {mib:.0f} MiB per-worker budget (plus "
                 "300 MiB) and was stopped; raise memory_per_worker_mb or use fewer workers")


def scan_budget(job: Job) -> tuple[int, str]:
    """(bytes, where it came from) a scan is held to: ``memory_per_worker_mb`` (or the batch's
    default, :func:`splatdeform.memory.worker_budget`, set on the job by ``run_batch``), else
    (a Dask worker without it) this machine's default budget, half its RAM
    (:func:`splatdeform.memory.default_budget`). Either way a cap, as ``--memory-budget`` is
    for ``deform``: several scans share the machine."""
    from ..memory import default_budget

    if job.memory_budget is not None:
        return int(job.memory_budget), "memory_per_worker_mb"
    return default_budget(), "half this worker's RAM (memory_per_worker_mb unset)"


def scan_options(job: Job, cfg):
    """The streaming options of a scan's edit: its budget (:func:`scan_budget`, or the edit's
    own ``memory_budget`` when smaller), streamed quietly on this worker. A scan over it
    streams where ``deform --memory-budget`` would, and is refused where deform would be."""
    from splatdeform.edit.stream import StreamOptions

    from ..memory import budget_bytes

    budget, name = scan_budget(job)
    own = budget_bytes(None, cfg.memory_budget)
    if own is not None and own < budget:
        budget, name = own, "memory_budget"
    return StreamOptions(budget=budget, quiet=True, budget_name=name)


def budget_check(job: Job, need: int, p) -> None:
    """A scan that does not stream (an archive member, or a budget below the 64 MiB a
    streamed run needs) must fit its budget (:func:`scan_budget`), by the one budget rule
    (:func:`splatdeform.memory.choose`); over it, one line naming the estimate and the
    budget."""
    from ..errors import InputError
    from ..memory import choose

    budget, source = scan_budget(job)
    what = ("MiB per worker; use fewer workers or set memory_per_worker_mb"
            if source == "memory_per_worker_mb" else "MiB available on this worker")
    choice = choose(need, budget, streamable=False, name=job.scan.name)
    if choice.mode == "refuse":
        mib = 2**20
        raise InputError(f"{job.scan.name}: needs about {need / mib:.0f} MiB for "
                         f"{p.points:,} points in {p.size / mib:.1f} MiB (the in-memory "
                         f"estimate), more than the {budget / mib:.0f} {what}")


def _vm_data() -> int:
    """Bytes of this process's data segment and private writable mappings (what RLIMIT_DATA
    counts); 0 where /proc is not there."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmData:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def cap_memory(budget: float | None) -> None:
    """Cap this worker process's memory for the next scan: RLIMIT_DATA (private writable
    memory; unlike RLIMIT_AS it ignores the address space OpenCL/LLVM and thread stacks only
    reserve) at what is mapped now plus the scan's budget plus :data:`CAP_SLACK_BYTES`. A
    scan that outgrows its estimate then gets MemoryError (a failed row) instead of pushing
    the machine into swap or the OOM killer. Only the soft limit moves, so the next scan can
    get its own. No budget: no cap."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_DATA)
    want = resource.RLIM_INFINITY if budget is None else \
        int(_vm_data() + budget + CAP_SLACK_BYTES)
    if hard != resource.RLIM_INFINITY:
        want = hard if want == resource.RLIM_INFINITY else min(want, hard)
    resource.setrlimit(resource.RLIMIT_DATA, (want, hard))


def _watch_parent(parent: int) -> None:
    while True:
        time.sleep(0.5)
        if os.getppid() != parent:   # the batch was killed: stop instead of finishing orphaned
            os.kill(os.getpid(), signal.SIGTERM)   # work, unwinding (temp folders) if we can
            time.sleep(5.0)
            os._exit(1)


def _terminated(signum: int, frame: Any) -> None:
    raise SystemExit(128 + signum)   # unwinds: temp folders and atomic outputs are cleaned up


def worker_init(parent: int | None = None) -> None:
    """Worker process set-up: SIGTERM unwinds (cleanup handlers run) and, given the batch
    process's pid, exit when that process dies."""
    signal.signal(signal.SIGTERM, _terminated)
    if parent is not None:
        threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()


def warm_up() -> None:
    """Import what a scan needs, so a per-scan timeout measures the scan, not the imports."""
    from splatdeform import io  # noqa: F401
    from splatdeform.edit import config  # noqa: F401
    from splatdeform.edit import run as edit  # noqa: F401

    from . import probe, sources  # noqa: F401
