"""The streaming second pass (basis + apply chunk by chunk) locally or on Dask, and
:func:`stream_deform` (plan + second pass) that :func:`splatdeform.edit.stream.run_stream` calls.

Every chunk is deformed by the same code as the in-memory path (:func:`splatdeform.deform.apply`
on a chunk-sized :class:`~splatdeform.deform.Deformation`), so fixed and handle points are
bit-exact and free points differ only by the basis backend's rounding. On Dask, workers read
their chunk from the shared file, deform it and write it as a part file (written to a temporary
name and renamed, so a recomputed chunk rewrites the same part); the client then assembles the
parts in order into the output, atomically. The fitted deformation (centers, weights, frame,
delta_c) is scattered once.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
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


def deform_chunk(src: ChunkFile, start: int, stop: int, labels: np.ndarray,
                 shared: Shared):
    """Deform points [start, stop): returns (rows or records, PLY properties or None). Free
    points by one-shot evaluation of d(x) and J(x) (:mod:`splatdeform.basis.oneshot`): the
    chunk's basis is never stored."""
    from splatdeform.basis.oneshot import deferred_basis

    model = src.read(start, stop)
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
    n = stop - start
    empty = np.empty(0, dtype=np.int64)
    deformation = df.Deformation(
        n_points=n, fixed=labels == FIXED, moving=labels == HANDLE, free_idx=free,
        moving_idx=mov, moving_coords=frame.coordinates(model.positions[mov]),
        moving_gradients=np.broadcast_to(grads, (mov.size, 4, 3)),
        constraint_idx=empty, constraint_points=np.empty((0, 3)),
        constraint_rhs=np.empty((0, 4)), control_points=frame.control_points,
        fit=shared.fit, basis=basis,
        groups=[df.Group("regions.handle", (0, 4), np.arange(mov.size), frame)])
    out = df.apply(deformation, model, shared.delta_c, moving_matrix=shared.matrix,
                   covariance=shared.covariance, split="off")  # chunks keep their counts
    if not np.isfinite(out.positions).all():
        raise ProcessingError("the deformation produced non-finite positions; check the "
                              "regions and the transform")
    try:
        return src.encode(out)
    except ProcessingError as exc:
        raise ProcessingError(
            f"{src.path}: deformed coordinates overflow the LAS int32 range with the input's "
            "scale and offset; the streaming path keeps them (run in memory with a larger "
            "--memory-budget to move the offset)") from exc


def _part_name(parts: Path, start: int) -> Path:
    return parts / f"part_{start:014d}.npy"


def dask_part(path: str, start: int, stop: int, labels: np.ndarray, shared: Shared,
              parts: str) -> str:
    """A Dask task: deform one chunk and write it as a part (idempotent: tmp + rename).

    Returns "" without writing when the parts folder is gone: the run was stopped (Ctrl-C,
    SIGTERM, an error) and removed it; a task still running then must not bring it back (which
    is why this does not use :func:`atomic_write`, which creates missing folders)."""
    folder = Path(parts)
    if not folder.is_dir():
        return ""
    src = open_chunks(path)
    rows, _ = deform_chunk(src, start, stop, labels, shared)
    final = _part_name(folder, start)
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
                      quiet: bool) -> None:
    progress = Progress("pass 5 (basis + apply + write)", src.n_points, quiet=quiet)
    map_chunks(src, out, lambda a, b: deform_chunk(src, a, b, plan.labels[a:b], shared), chunk,
               progress=progress.update, read_ahead=True)
    progress.finish()


def second_pass_dask(src: ChunkFile, plan: Plan, shared: Shared, out: Path, chunk: int,
                     quiet: bool, client) -> None:
    from distributed import as_completed

    parts = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.stem}.parts."))
    progress = Progress("pass 5 on Dask (basis + apply + parts)", src.n_points, quiet=quiet)
    futures = {}
    try:
        shared_f = client.scatter(shared, broadcast=True)
        for a, b in chunk_ranges(src.n_points, chunk):
            fut = client.submit(dask_part, str(src.path), a, b, plan.labels[a:b], shared_f,
                                str(parts), key=f"splatdeform-part-{a}-{b}-{id(plan)}",
                                retries=2, pure=False)
            futures[fut] = (a, b)
        for fut in as_completed(list(futures)):
            fut.result()
            a, b = futures[fut]
            progress.update(b - a)
        progress.finish()
        props = _out_props(src, plan, shared)
        map_chunks(src, out, lambda a, _b: (np.load(_part_name(parts, a), allow_pickle=False),
                                            props), chunk)
    finally:
        with deferred_signals():  # a second Ctrl-C must not leave the folder behind
            _remove_parts(parts, futures)


def stream_deform(src: ChunkFile, cfg, base_dir: Path, out: Path, *, chunk: int,
                  quiet: bool = False, client=None, max_border: int = 20_000_000,
                  max_handle: int = 2**62, check_fit=None):
    """Plan (passes 1-4, rings, fit) and the second pass. Returns the plan (its timings with
    the second pass's as ``apply``)."""
    from splatdeform.edit.plain import handle_matrix, make_fit_fn

    plan = build_plan(src, cfg, base_dir, chunk=chunk, quiet=quiet, max_border=max_border,
                      make_fit_fn=make_fit_fn, handle_matrix=handle_matrix,
                      max_handle=max_handle)
    if check_fit is not None:
        check_fit(plan.border.fit)  # warns, or raises before any output
    shared = Shared(plan.border.fit, plan.frame, plan.matrix, plan.delta_c, cfg.backend,
                    cfg.device, cfg.gaussians.covariance)
    t0 = time.perf_counter()
    if client is None:
        second_pass_local(src, plan, shared, out, chunk, quiet)
    else:
        second_pass_dask(src, plan, shared, out, chunk, quiet, client)
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
