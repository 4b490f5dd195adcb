"""The streaming second pass (basis + apply chunk by chunk) locally or on Dask, and
:func:`stream_deform` (plan + second pass) that :func:`splatdeform.edit.stream.run_stream` calls.

Every chunk is deformed by the same code as the in-memory path (:func:`splatdeform.deform.apply`
on a chunk-sized :class:`~splatdeform.deform.Deformation`), so fixed and handle points are
bit-exact and free points differ only by the basis backend's rounding. On Dask, workers read
their chunk from the shared file, deform it and write it as a part file (written to a temporary
name and renamed, so a recomputed chunk rewrites the same part); the client then assembles the
parts in order into the output, atomically. The fitted deformation (centers, weights, frame,
delta_c) is scattered once. With ``gaussians.split: auto`` a split test pass decides which
splats split before pass 5 (:mod:`splatdeform.edit.stream.split`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splatdeform import deform as df
from splatdeform.basis.result import Basis
from splatdeform.dask_client import dask_client  # noqa: F401 - run_stream's client
from splatdeform.deform.gaussians import DEFAULT_COVARIANCE
from splatdeform.edit.stream.plan import FIXED, FREE, HANDLE, Plan, build_plan, chunk_ranges
from splatdeform.edit.stream.progress import Progress
from splatdeform.errors import InputError, ProcessingError
from splatdeform.interrupts import deferred_signals
from splatdeform.io import FORMATS, ChunkFile, extension_of, open_chunks
from splatdeform.io.chunks import map_chunks


@dataclass
class Shared:
    """What every chunk needs (small; sent once to Dask workers)."""

    fit: object
    frame: object
    matrix: np.ndarray
    delta_c: np.ndarray
    backend: str
    device: str | None
    covariance: str = DEFAULT_COVARIANCE  # gaussians.covariance
    split: str = "off"  # gaussians.split


def chunk_deformation(model, labels: np.ndarray, shared: Shared) -> df.Deformation:
    """The chunk's :class:`~splatdeform.deform.Deformation`: free points by one-shot
    evaluation of d(x) and J(x) (:mod:`splatdeform.basis.oneshot`, never stored), handle
    points by the frame."""
    from splatdeform.basis.oneshot import deferred_basis

    free = np.flatnonzero(labels == FREE)
    mov = np.flatnonzero(labels == HANDLE)
    frame = shared.frame
    needs_grad = any(a is not None for a in (model.normals, model.axes, model.gaussians))
    if free.size:
        basis = deferred_basis(model.positions[free], shared.fit, gradients=needs_grad,
                               backend=shared.backend, device=shared.device)
    else:
        k = shared.fit.weights.shape[1]
        basis = Basis(np.zeros((0, k)), np.zeros((0, k, 3)) if needs_grad else None)
    grads = frame.coordinate_gradients()
    n = labels.size
    empty = np.empty(0, dtype=np.int64)
    return df.Deformation(
        n_points=n, fixed=labels == FIXED, moving=labels == HANDLE, free_idx=free,
        moving_idx=mov, moving_coords=frame.coordinates(model.positions[mov]),
        moving_gradients=np.broadcast_to(grads, (mov.size, 4, 3)),
        constraint_idx=empty, constraint_points=np.empty((0, 3)),
        constraint_rhs=np.empty((0, 4)), control_points=frame.control_points,
        fit=shared.fit, basis=basis,
        groups=[df.Group("regions.handle", (0, 4), np.arange(mov.size), frame)])


def _finite(model) -> None:
    if not np.isfinite(model.positions).all():
        raise ProcessingError("the deformation produced non-finite positions; check the "
                              "regions and the transform")


def deform_chunk(src: ChunkFile, start: int, stop: int, labels: np.ndarray,
                 shared: Shared, split: tuple[np.ndarray, np.ndarray] | None = None,
                 children: Callable[[np.ndarray], None] | None = None):
    """Deform points [start, stop): returns (rows or records, PLY properties or None).
    ``split``: (chunk rows (P,), counts (P, 3)) of the splats that split (the split test's
    :class:`~splatdeform.edit.stream.split.Decision`): their rows hold child 0 and
    ``children(records)`` receives the other children's records, in order."""
    model = src.read(start, stop)
    deformation = chunk_deformation(model, labels, shared)
    out = df.apply(deformation, model, shared.delta_c, moving_matrix=shared.matrix,
                   covariance=shared.covariance, split="off")  # split below, as decided
    _finite(out)
    if split is not None and split[0].size:
        from splatdeform.edit.stream.split import chunk_children

        def emit(kids) -> None:
            _finite(kids)
            children(src.encode(kids)[0])

        chunk_children(model, out, deformation, shared.delta_c, *split, shared.covariance, emit)
    try:
        return src.encode(out)
    except ProcessingError as exc:
        raise ProcessingError(
            f"{src.path}: deformed coordinates overflow the LAS int32 range with the input's "
            "scale and offset; the streaming path keeps them (run in memory with a larger "
            "--memory-budget to move the offset)") from exc


def chunk_wants(src: ChunkFile, start: int, stop: int, labels: np.ndarray, shared: Shared):
    """The split test of points [start, stop): the splats the rule wants to split
    (:func:`splatdeform.edit.stream.split.chunk_wants`)."""
    from splatdeform.edit.stream import split as ss

    model = src.read(start, stop)
    return ss.chunk_wants(model, chunk_deformation(model, labels, shared), shared.delta_c,
                          start)


def dask_wants(path: str, start: int, stop: int, labels: np.ndarray, shared: Shared):
    """A Dask task: the split test of one chunk (small arrays back)."""
    with open_chunks(path) as src:
        return chunk_wants(src, start, stop, labels, shared)


def may_split(src: ChunkFile, shared: Shared) -> bool:
    """True when a streamed edit may split splats: ``gaussians.split: auto``, a file of
    splats or surfel discs with axes and a field with an RBF part (an affine field never
    splits)."""
    from splatdeform.deform.split_surfel import splittable

    if shared.split != "auto" or not src.n_points or not splittable(src.read(0, 1)):
        return False
    return bool(np.any(np.asarray(shared.fit.weights, np.float64)[4:] @ shared.delta_c))


def split_test(src: ChunkFile, plan: Plan, shared: Shared, chunk: int, quiet: bool,
               client=None, shared_f=None):
    """The split test pass (:mod:`splatdeform.edit.stream.split`): which splats split, the
    growth cap over the whole file applied. None when nothing can split. On Dask
    (``client``), ``shared_f``: ``shared`` scattered once for the whole run."""
    from splatdeform.edit.stream.split import decide

    if not may_split(src, shared):
        return None
    progress = Progress("split test (which splats split)", src.n_points, quiet=quiet)
    ranges = list(chunk_ranges(src.n_points, chunk))
    if client is None:
        wants = []
        for a, b in ranges:
            wants.append(chunk_wants(src, a, b, plan.labels[a:b], shared))
            progress.update(b - a)
    else:
        futures = [client.submit(dask_wants, str(src.path), a, b, plan.labels[a:b], shared_f,
                                 key=f"splatdeform-wants-{a}-{b}-{id(plan)}", retries=2,
                                 pure=False) for a, b in ranges]
        wants = []
        for fut, (a, b) in zip(futures, ranges, strict=True):
            wants.append(fut.result())
            progress.update(b - a)
    progress.finish()
    moved = int(src.n_points - np.count_nonzero(plan.labels == FIXED))
    return decide(wants, moved)


def _part_name(parts: Path, start: int, what: str = "part") -> Path:
    return parts / f"{what}_{start:014d}.npy"


def _save_part(folder: Path, final: Path, rows: np.ndarray) -> str:
    """Write ``rows`` as ``final`` (tmp + rename); "" when the folder is gone."""
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{final.stem}.", suffix=".tmp")
    except FileNotFoundError:
        return ""
    try:
        with os.fdopen(fd, "wb") as f:
            np.save(f, rows, allow_pickle=False)
        os.replace(tmp, final)
    except FileNotFoundError:
        return ""
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    return str(final)


def dask_part(path: str, start: int, stop: int, labels: np.ndarray, shared: Shared,
              parts: str, split: tuple[np.ndarray, np.ndarray] | None = None) -> str:
    """A Dask task: deform one chunk and write it as a part (idempotent: tmp + rename); with
    ``split`` (see :func:`deform_chunk`) its children other than child 0 as a children part.

    Returns "" without writing when the parts folder is gone: the run was stopped (Ctrl-C,
    SIGTERM, an error) and removed it; a task still running then must not bring it back (which
    is why this does not use :func:`atomic_write`, which creates missing folders)."""
    folder = Path(parts)
    if not folder.is_dir():
        return ""
    kids: list[np.ndarray] = []
    with open_chunks(path) as src:
        rows, _ = deform_chunk(src, start, stop, labels, shared, split, kids.append)
    if kids and not _save_part(folder, _part_name(folder, start, "children"),
                               np.concatenate(kids)):
        return ""
    return _save_part(folder, _part_name(folder, start), rows)


def _remove_parts(parts: Path, futures) -> None:
    """Cancel the part tasks and remove the parts folder; a task that was already running may
    still be renaming its part in, so a few tries."""
    with contextlib.suppress(Exception):
        for fut in futures:
            fut.cancel()
    for _ in range(50):
        shutil.rmtree(parts, ignore_errors=True)
        if not parts.exists():
            return
        time.sleep(0.1)


def _out_props(src: ChunkFile, plan: Plan, shared: Shared):
    """The output properties (from deforming a one-point chunk)."""
    _, props = deform_chunk(src, 0, 1, plan.labels[:1], shared)
    return props


def second_pass_local(src: ChunkFile, plan: Plan, shared: Shared, out: Path, chunk: int,
                      quiet: bool, decision=None) -> None:
    """Pass 5 in this process; ``decision``: the split test's (None: nothing splits), its
    children spilled beside the output and appended after the chunks."""
    from splatdeform.edit.stream.split import Spill

    progress = Progress("pass 5 (basis + apply + write)", src.n_points, quiet=quiet)
    if decision is None or not decision.rows.size:
        map_chunks(src, out, lambda a, b: deform_chunk(src, a, b, plan.labels[a:b], shared),
                   chunk, progress=progress.update, read_ahead=True)
    else:
        spill = Spill(out)
        try:
            map_chunks(src, out, lambda a, b: deform_chunk(
                src, a, b, plan.labels[a:b], shared, decision.within(a, b), spill.write),
                chunk, progress=progress.update, read_ahead=True, extra=decision.extra,
                appendix=lambda: spill.blocks(chunk))
        finally:
            spill.close()
    progress.finish()


def second_pass_dask(src: ChunkFile, plan: Plan, shared: Shared, out: Path, chunk: int,
                     quiet: bool, client, decision=None, shared_f=None) -> None:
    from distributed import as_completed

    parts = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.stem}.parts."))
    progress = Progress("pass 5 on Dask (basis + apply + parts)", src.n_points, quiet=quiet)
    futures = {}
    try:
        if shared_f is None:
            shared_f = client.scatter(shared, broadcast=True)
        for a, b in chunk_ranges(src.n_points, chunk):
            split = None if decision is None else decision.within(a, b)
            fut = client.submit(dask_part, str(src.path), a, b, plan.labels[a:b], shared_f,
                                str(parts), split, key=f"splatdeform-part-{a}-{b}-{id(plan)}",
                                retries=2, pure=False)
            futures[fut] = (a, b)
        for fut in as_completed(list(futures)):
            fut.result()
            a, b = futures[fut]
            progress.update(b - a)
        progress.finish()
        props = _out_props(src, plan, shared)
        kids = [a for a, _ in chunk_ranges(src.n_points, chunk)
                if _part_name(parts, a, "children").is_file()]
        map_chunks(src, out, lambda a, _b: (np.load(_part_name(parts, a), allow_pickle=False),
                                            props), chunk,
                   extra=0 if decision is None else decision.extra,
                   appendix=lambda: (np.load(_part_name(parts, a, "children"),
                                             allow_pickle=False) for a in kids))
    finally:
        with deferred_signals():  # a second Ctrl-C must not leave the folder behind
            _remove_parts(parts, futures)


def stream_deform(src: ChunkFile, cfg, base_dir: Path, out: Path, *, chunk: int,
                  quiet: bool = False, client=None, max_border: int = 20_000_000,
                  max_handle: int = 2**62, check_fit=None):
    """Plan (passes 1-4, rings, fit) and the second pass. Returns the plan (its timings with
    the second pass's as ``apply``)."""
    from splatdeform.edit.plain import handle_matrix, make_fit_fn
    from splatdeform.edit.stream.poscache import cached_positions

    cache = cached_positions(src, out)   # a LAZ: decoded once for passes 1-4, not four times
    try:
        plan = build_plan(src if cache is None else cache, cfg, base_dir, chunk=chunk,
                          quiet=quiet, max_border=max_border, make_fit_fn=make_fit_fn,
                          handle_matrix=handle_matrix, max_handle=max_handle)
    finally:
        if cache is not None:
            cache.close()
    if check_fit is not None:
        check_fit(plan.border.fit)  # warns, or raises before any output
    shared = Shared(plan.border.fit, plan.frame, plan.matrix, plan.delta_c, cfg.backend,
                    cfg.device, cfg.gaussians.covariance, cfg.gaussians.split)
    t0 = time.perf_counter()
    # one scatter for both passes (scattering the same object twice shares its key)
    shared_f = None if client is None else client.scatter(shared, broadcast=True)
    plan.split = split_test(src, plan, shared, chunk, quiet, client, shared_f)
    plan.timings["split_test"] = time.perf_counter() - t0   # part of apply, as in memory
    if client is None:
        second_pass_local(src, plan, shared, out, chunk, quiet, plan.split)
    else:
        second_pass_dask(src, plan, shared, out, chunk, quiet, client, plan.split, shared_f)
    plan.timings["apply"] = time.perf_counter() - t0
    return plan


def check_streamable(cfg, in_path: Path, out_path: Path) -> ChunkFile:
    """The chunk reader, or an InputError saying why this edit cannot stream (the one rule,
    :func:`splatdeform.edit.stream.stream_refusal`)."""
    from splatdeform.edit.capable import stream_refusal

    why = stream_refusal(cfg)
    if why:
        raise InputError(f"{why}; raise --memory-budget")
    src = open_chunks(in_path)
    out_format = FORMATS.get(extension_of(out_path))  # x.compressed.ply is not a plain PLY
    if out_format is None or out_format.chunks is None or not isinstance(src, out_format.chunks):
        raise InputError(f"{out_path}: streaming writes the input's format "
                         f"({extension_of(in_path)}); choose a matching output extension")
    return src
