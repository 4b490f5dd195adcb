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
choice stream-or-not is the pre-flight's (:func:`splatdeform.edit.plan.plan_edit`, with
:class:`StreamOptions`);
the chunk readers are the io format table's (:func:`splatdeform.io.open_chunks`), the border
geometry :mod:`splatdeform.deform.border`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splatdeform.edit.capable import stream_refusal
from splatdeform.edit.result import EditResult, edit_stats
from splatdeform.edit.stream.progress import Progress
from splatdeform.io import COSTED as io_costed
from splatdeform.io import STREAMABLE, extension_of
from splatdeform.memory import budget_bytes, default_budget, machine_memory, parse_size


@dataclass(frozen=True)
class StreamOptions:
    """How ``deform`` may run out of core: ``budget`` in bytes or a size string like '2GB'
    (None: the config's ``memory_budget``, else half the RAM); a Dask ``scheduler`` address or
    a number of local ``workers`` (either one makes the edit stream); ``quiet``: no progress
    or streaming lines; ``budget_name``: where the budget came from, for the refusal line
    (default ``--memory-budget`` when ``budget`` is given, else ``memory_budget``; batch:
    ``memory_per_worker_mb``)."""

    budget: int | str | None = None
    scheduler: str | None = None
    workers: int | None = None
    quiet: bool = False
    budget_name: str | None = None

    @property
    def distributed(self) -> bool:
        return bool(self.scheduler or self.workers)

    def budget_bytes(self, cfg) -> int | None:
        """``budget`` in bytes, else ``cfg.memory_budget``'s (ConfigError naming the flag or
        key when malformed), else None (half the RAM)."""
        return budget_bytes(self.budget, cfg.memory_budget)


#: formats whose in-memory estimate comes from their validated header (memory.file_cost): the
#: ones whose declaration has a header probe (splatdeform.io), splat formats included
COSTED = io_costed


def edit_choice(cfg, in_path: Path, budget: int | None, *, whole: str | None = None,
                budget_name: str = "--memory-budget"):
    """The budget rule (:func:`splatdeform.memory.choose`) for this edit's input: in memory,
    stream or refuse, from the in-memory estimate of the input's validated header. ``budget``:
    the explicit budget (None: half the RAM); ``whole``: ``--reuse`` / ``--drop-nonfinite`` when
    given (they need the whole model); ``budget_name``: the flag or key the budget came from,
    for the refusal line. Raises FormatError/InputError for a header the reader
    would refuse (one line, before anything is loaded)."""
    from splatdeform import memory

    ext = extension_of(in_path)
    in_path = Path(in_path)
    if ext not in COSTED or not in_path.is_file():   # estimated when loaded (splat formats)
        return memory.choose(0, budget, streamable=False, name=in_path)
    cost = memory.file_cost(in_path)
    from splatdeform.deform.split import GROWTH_CAP

    need = memory.deform_peak(cost, cfg.boundary.neighbors, cfg.fit.max_centers,
                              stored=whole == "--reuse",
                              growth=GROWTH_CAP if cfg.gaussians.split == "auto" else 0.0)
    why = "" if ext in STREAMABLE else f"{ext} files do not stream"
    why = why or stream_refusal(cfg)
    # decided here, once: an edit that cannot stream runs in memory under the default budget
    # (with a warning) and is refused over an explicit one
    return memory.choose(need, budget, streamable=not why, name=in_path, whole=whole,
                         why_not=why, budget_name=budget_name)


def should_stream(cfg, in_path: Path, budget: int | None) -> bool:
    """True when the input is streamable and its in-memory peak (the one estimator,
    :mod:`splatdeform.memory`) exceeds the budget."""
    from splatdeform.errors import SplatdeformError

    if extension_of(in_path) not in STREAMABLE or not Path(in_path).is_file():
        return False
    try:
        return edit_choice(cfg, in_path, budget).mode == "stream"
    except SplatdeformError:   # an unreadable header: the in-memory loader says why
        return False


def run_stream(cfg, base_dir: str | Path = ".", *, output: str | Path | None = None,
               budget: int | None = None, scheduler: str | None = None,
               workers: int | None = None, quiet: bool = False, log=None, check_fit=None,
               client=None, chunk: int | None = None,
               max_handle: int | None = None) -> EditResult:
    """Run one handle edit out of core (locally, or on Dask with ``scheduler``/``workers``).

    ``cfg``: an :class:`~splatdeform.edit.plan.EditPlan` (what ``run_edit`` passes: its paths
    were checked and its budget and Dask options decided by the pre-flight; ``base_dir``,
    ``output``, ``budget``, ``scheduler``, ``workers`` and ``quiet`` come from it), or an
    EditConfig with ``base_dir`` (the output path is checked here).
    Returns an :class:`~splatdeform.edit.result.EditResult` with ``model``/``deformed`` None
    (the models are never whole in memory) and the figures ``format_report`` prints.
    ``client``: an open Dask client to use; ``chunk``: points per chunk (default: from the
    budget); ``max_handle``: most handle points kept whole for the frame (beyond: streamed
    moments)."""
    import time

    from splatdeform.edit.config import EditConfig
    from splatdeform.edit.stream.run import check_streamable, dask_client, stream_deform
    from splatdeform.memory import file_cost, stream_sizes

    if not isinstance(cfg, EditConfig):   # an EditPlan (edit.plan imports this module)
        plan_ = cfg
        cfg, base_dir, in_path, out_path = plan_.cfg, plan_.base_dir, plan_.input, plan_.output
        budget, options = plan_.budget, plan_.options
        scheduler, workers, quiet = options.scheduler, options.workers, options.quiet
    else:
        from splatdeform.io import check_output_path

        base_dir = Path(base_dir)
        in_path = base_dir / cfg.input
        out_path = Path(output) if output is not None else base_dir / cfg.output
        check_output_path(out_path, in_path)
    budget = budget or default_budget()
    t0 = time.perf_counter()
    src = check_streamable(cfg, in_path, out_path)
    n = src.n_points
    # interpreter and libraries, labels, what the reader holds besides its rows (a LAZ chunk)
    sizes = stream_sizes(budget, n, src.record_bytes, file_cost(in_path).reader_bytes)
    chunk = chunk or sizes.chunk
    max_border = sizes.max_border
    if max_handle is None:
        max_handle = sizes.max_handle
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
    if plan.split is not None:   # gaussians.split: auto, decided by the split test pass
        stats.update(plan.split.stats())
    timings = dict(plan.timings)
    timings["load"] = sum(timings.pop(k, 0.0) for k in ("bbox", "regions", "border"))
    timings["total"] = time.perf_counter() - t0
    return EditResult(None, None, plan.border, plan.delta_c, plan.matrix, out_path, stats,
                      timings)


__all__ = ["Progress", "StreamOptions", "budget_bytes", "default_budget", "edit_choice",
           "machine_memory", "parse_size", "run_stream", "should_stream"]
