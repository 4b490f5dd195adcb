"""Out-of-core ``deform``: scans bigger than memory, and one scan split over a Dask cluster.

``deform`` streams when the in-memory path's estimated peak memory exceeds the budget
(``--memory-budget`` / config ``memory_budget``; default half the machine's RAM), or when it is
given a Dask scheduler (``--scheduler``) or local worker processes (``--workers``):

1. pass 1: bounding box (and a sample for the kNN scale); pass 2: regions -> one label byte
   per point, handle positions (frame, pivot);
2. passes 3-4: the border set (points near another label), rings on it, the fit (once);
3. pass 5: per chunk, basis of the free points + apply (the in-memory code on a chunk) ->
   the output file (same format and properties), renamed into place at the end.

See :mod:`splatdeform.edit.stream.plan` for why the rings equal the in-memory rings. The
choice stream-or-not is :func:`splatdeform.edit.run.run_edit`'s (with :class:`StreamOptions`);
the chunk readers are the io format table's (:func:`splatdeform.io.open_chunks`), the border
geometry :mod:`splatdeform.deform.border`.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splatdeform.edit.result import EditResult, edit_stats
from splatdeform.edit.stream.progress import Progress
from splatdeform.errors import ConfigError
from splatdeform.io import STREAMABLE, extension_of

_UNITS = {"": 1, "b": 1, "k": 2**10, "kb": 2**10, "kib": 2**10, "m": 2**20, "mb": 2**20,
          "mib": 2**20, "g": 2**30, "gb": 2**30, "gib": 2**30, "t": 2**40, "tb": 2**40,
          "tib": 2**40}


def parse_size(text: str | int | float, what: str = "--memory-budget") -> int:
    """'512MB', '1.5GB', '2g', 1000000 -> bytes (ConfigError naming ``what`` otherwise)."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        value = int(text)
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([a-zA-Z]*)\s*", str(text))
        if not m or m.group(2).lower() not in _UNITS:
            raise ConfigError(f"{what}: expected a size like 512MB or 2GB, got {text!r}")
        value = int(float(m.group(1)) * _UNITS[m.group(2).lower()])
    if value < 64 * 2**20:
        raise ConfigError(f"{what}: expected at least 64MB, got {text!r}")
    return value


@dataclass(frozen=True)
class StreamOptions:
    """How ``deform`` may run out of core: ``budget`` in bytes or a size string like '2GB'
    (None: the config's ``memory_budget``, else half the RAM); a Dask ``scheduler`` address or
    a number of local ``workers`` (either one makes the edit stream); ``quiet``: no progress
    or streaming lines."""

    budget: int | str | None = None
    scheduler: str | None = None
    workers: int | None = None
    quiet: bool = False

    @property
    def distributed(self) -> bool:
        return bool(self.scheduler or self.workers)

    def budget_bytes(self, cfg) -> int | None:
        """``budget`` in bytes, else ``cfg.memory_budget``'s (ConfigError naming the flag or
        key when malformed), else None (half the RAM)."""
        return budget_bytes(self.budget, cfg.memory_budget)


def budget_bytes(flag: int | str | None, config_value: int | str | None = None) -> int | None:
    """The memory budget in bytes: ``--memory-budget`` (``flag``), else the config's
    ``memory_budget``, else None (the caller's default: half the RAM). A malformed value is a
    ConfigError naming the flag or the key."""
    if flag is not None:
        return parse_size(flag) if isinstance(flag, str) else int(flag)
    return None if config_value is None else parse_size(config_value, "memory_budget")


def machine_memory() -> int:
    """Physical memory in bytes."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8 * 2**30


def default_budget() -> int:
    """Half the machine's RAM."""
    return machine_memory() // 2


def should_stream(cfg, in_path: Path, budget: int | None) -> bool:
    """True when the input is streamable and its in-memory peak (the one estimator,
    :mod:`splatdeform.memory`) exceeds the budget."""
    from splatdeform import memory
    from splatdeform.errors import SplatdeformError

    if extension_of(in_path) not in STREAMABLE or not Path(in_path).is_file():
        return False
    try:
        cost = memory.file_cost(in_path)
    except SplatdeformError:   # an unreadable header: the in-memory loader says why
        return False
    return memory.deform_peak(cost, cfg.boundary.neighbors) > (budget or default_budget())


def run_stream(cfg, base_dir: str | Path = ".", *, output: str | Path | None = None,
               budget: int | None = None, scheduler: str | None = None,
               workers: int | None = None, quiet: bool = False, log=None, check_fit=None,
               client=None, chunk: int | None = None,
               max_handle: int | None = None) -> EditResult:
    """Run one handle edit out of core (locally, or on Dask with ``scheduler``/``workers``).

    Returns an :class:`~splatdeform.edit.result.EditResult` with ``model``/``deformed`` None
    (the models are never whole in memory) and the figures ``format_report`` prints.
    ``client``: an open Dask client to use; ``chunk``: points per chunk (default: from the
    budget); ``max_handle``: most handle points kept whole for the frame (beyond: streamed
    moments)."""
    import time

    from splatdeform.edit.stream.run import check_streamable, dask_client, stream_deform
    from splatdeform.io import check_output_path
    from splatdeform.memory import BASE_BYTES, stream_caps, stream_chunk

    base_dir = Path(base_dir)
    in_path = base_dir / cfg.input
    out_path = Path(output) if output is not None else base_dir / cfg.output
    check_output_path(out_path, in_path)
    budget = budget or default_budget()
    t0 = time.perf_counter()
    src = check_streamable(cfg, in_path, out_path)
    n = src.n_points
    base = BASE_BYTES + 2 * n  # interpreter and libraries, labels
    chunk = chunk or stream_chunk(budget, src.record_bytes, fixed_bytes=base)
    max_border, whole_handle = stream_caps(budget, base)
    if max_handle is None:
        max_handle = whole_handle
    if log and not quiet:
        log(f"streaming {n:,} points in chunks of {chunk:,} (memory budget "
            f"{budget / 2**20:,.0f} MB)")
    if client is None and (scheduler or workers):  # at least ~16 parts: several per worker
        chunk = min(chunk, max(20_000, -(-n // 16)))
        with dask_client(scheduler, workers) as client:
            plan = stream_deform(src, cfg, base_dir, out_path, chunk=chunk, quiet=quiet,
                                 client=client, max_border=max_border, check_fit=check_fit,
                                 max_handle=max_handle)
    else:
        plan = stream_deform(src, cfg, base_dir, out_path, chunk=chunk, quiet=quiet,
                             client=client, max_border=max_border, check_fit=check_fit,
                             max_handle=max_handle)
    stats = edit_stats(plan.border, plan.delta_c, points=n,
                       free_points=int(np.count_nonzero(plan.labels == 0)),
                       diagonal=float(np.linalg.norm(plan.hi - plan.lo)) or 1.0,
                       border_points=plan.border_points, chunk=chunk)
    timings = dict(plan.timings)
    timings["load"] = sum(timings.pop(k, 0.0) for k in ("bbox", "regions", "border"))
    timings["total"] = time.perf_counter() - t0
    return EditResult(None, None, plan.border, plan.delta_c, plan.matrix, out_path, stats,
                      timings)


__all__ = ["Progress", "StreamOptions", "default_budget", "parse_size", "run_stream",
           "should_stream"]
