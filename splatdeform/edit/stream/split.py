"""``gaussians.split: auto`` on a streamed or Dask ``deform``: the in-memory rule, decided once
for the whole file before anything is written (issue 46).

The rule (:mod:`splatdeform.deform.split`) decides each free splat from that splat alone (its J
at the centre and the field at its sigma points); only the growth cap looks at every splat at
once. So a *split test* pass reads the file a chunk at a time and keeps the splats the rule
wants to split (row, children per axis, excess: 19 bytes each, never the others), then the cap
runs on all of them as in memory. Pass 5 then knows which splats split and the exact output
count (the PLY header, written first, counts the children): each chunk writes its rows with a
split parent's row holding its child 0, and the other children (in parent-row, child order) go
to a spill file (Dask: one children part per chunk) appended after every original row. The
output is the in-memory file's rows in the in-memory order: byte-identical where the backend
gives each point the same values whatever the chunking (one-shot evaluation does). Surfel discs
with tangent axes split the same way (:mod:`splatdeform.deform.split_surfel`).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splatdeform.deform import split as sp
from splatdeform.deform import split_surfel as ssf

#: at most this many children deformed at once in pass 5 (bounds the temporaries of a
#: heavily split chunk; a chunk's own size when smaller)
CHILD_BLOCK = 1 << 16


@dataclass
class Decision:
    """The split of a whole streamed file: ``rows`` (S,) int64 ascending, the splats that
    split; ``counts`` (S, 3) children per rest axis; ``capped``: splats the rule wanted that
    the growth cap kept whole."""

    rows: np.ndarray
    counts: np.ndarray
    capped: int = 0

    @property
    def children(self) -> int:
        return int(self.counts.prod(axis=1).sum())

    @property
    def extra(self) -> int:
        """Records the output holds beyond the input's (children minus the parents)."""
        return self.children - int(self.rows.size)

    def within(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """(chunk-local rows (P,), counts (P, 3)) of the splats of rows [start, stop)."""
        a, b = np.searchsorted(self.rows, [start, stop])
        return self.rows[a:b] - start, self.counts[a:b]

    def stats(self) -> dict[str, int]:
        """split_splats, split_children, split_capped as the in-memory apply counts them."""
        return {"split_splats": int(self.rows.size), "split_children": self.children,
                "split_capped": int(self.capped)}


#: a chunk's wanted splits: (global rows (W,) int64, counts (W, 3) uint8, excess (W,))
Wants = tuple[np.ndarray, np.ndarray, np.ndarray]


def chunk_wants(model, deformation, delta_c: np.ndarray, start: int) -> Wants:
    """The splats of a chunk (rows from ``start``) the rule wants to split, before the cap:
    J at the free centres and the bend test through :func:`splatdeform.deform.split.fit_field`
    of the chunk's (one-shot) ``deformation``, as the in-memory apply computes them."""
    free = deformation.free_idx
    if not ssf.splittable(model) or free.size == 0:
        return np.zeros(0, np.int64), np.ones((0, 3), np.int64), np.zeros(0)
    field = sp.fit_field(deformation, delta_c)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        _, jac = field(model.positions[free], True)
        rows, want = ssf.wanted_any(model, free, jac, field)
    keep = want.split
    return (rows[keep].astype(np.int64) + start, want.counts[keep].astype(np.uint8),
            want.excess[keep])


def decide(wants: list[Wants], moved: int) -> Decision:
    """The growth cap (:func:`splatdeform.deform.split.cap` over ``moved`` non-fixed splats)
    on every chunk's wants, in row order (the in-memory tie order)."""
    if not wants:
        return Decision(np.zeros(0, np.int64), np.ones((0, 3), np.int64))
    rows = np.concatenate([w[0] for w in wants])
    counts = np.concatenate([w[1] for w in wants]).reshape(-1, 3).astype(np.int64)
    excess = np.concatenate([w[2] for w in wants])
    chosen = sp.cap(sp.SplitPlan(counts, excess), moved)
    keep = chosen.split
    return Decision(rows[keep], chosen.counts[keep], chosen.capped)


def chunk_children(model, out, deformation, delta_c: np.ndarray, rows: np.ndarray,
                   counts: np.ndarray, covariance: str, emit: Callable) -> None:
    """Split a deformed chunk: ``out`` (the chunk deformed whole, changed in place) gets each
    split parent's child 0 in its row; ``emit(children)`` receives the other children (a model
    per block of at most the chunk's size or :data:`CHILD_BLOCK` children, in parent-row then
    child order; each child depends on its parent alone, so blocks change nothing)."""
    from splatdeform.deform.model_apply import _transform_attributes, check_finite

    if rows.size == 0:
        return
    field = sp.fit_field(deformation, delta_c)
    per = counts.prod(axis=1)
    block = max(sp.MAX_CHILDREN, min(CHILD_BLOCK, model.n_points))
    edges = np.searchsorted(np.cumsum(per), np.arange(block, int(per.sum()), block),
                            side="right")
    for lo, hi in zip(np.r_[0, edges], np.r_[edges, rows.size], strict=True):
        if hi <= lo:
            continue
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            kids, deformed, _ = ssf.deformed_any(
                model, rows[lo:hi], counts[lo:hi], field, covariance=covariance,
                transform=_transform_attributes, dtype=out.positions.dtype)
        check_finite(sp.take(model, kids.parent), deformed)   # as the in-memory apply's check
        sp.put_first(out, kids, deformed)
        emit(sp.take(deformed, np.flatnonzero(kids.child != 0)))


class Spill:
    """Children's records of a local pass 5, in order, in a temporary file beside the output
    (removed on close): appended after every original row."""

    def __init__(self, out: Path) -> None:
        fd, name = tempfile.mkstemp(dir=out.parent, prefix=f".{out.stem}.children.",
                                    suffix=".tmp")
        self.path, self.file, self.dtype, self.count = Path(name), os.fdopen(fd, "w+b"), None, 0

    def write(self, records: np.ndarray) -> None:
        self.dtype = records.dtype
        self.file.write(np.ascontiguousarray(records).view(np.uint8))
        self.count += len(records)

    def blocks(self, size: int) -> Iterator[np.ndarray]:
        """The records written, ``size`` at a time."""
        if not self.count:
            return
        self.file.flush()
        self.file.seek(0)
        for _ in range(0, self.count, size):
            yield np.fromfile(self.file, dtype=self.dtype, count=size)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.file.close()
        with contextlib.suppress(OSError):
            os.unlink(self.path)


def field_split(fld, src, chunk: int, backend: str | None) -> Decision | None:
    """The split test of a streamed ``apply`` of a saved field ``fld`` (its
    ``gaussians.split``, default ``auto``) on the chunk file ``src``: the chunks' deformations
    as :meth:`splatdeform.field.Field.apply` makes them, the cap over the whole file's moved
    splats. None when nothing can split (``off``, no splats, an affine field)."""
    from splatdeform.io.chunks import chunk_ranges

    if fld.meta.get("gaussians", {}).get("split", sp.DEFAULT_SPLIT) != "auto" or \
            not src.n_points or not ssf.splittable(src.read(0, 1)) or \
            not np.any(np.asarray(fld.fit.weights, np.float64)[4:] @ fld.delta_c):
        return None
    wants, moved = [], 0
    for a, b in chunk_ranges(src.n_points, chunk):
        model = src.read(a, b)
        deformation = fld.deformation(model, backend)
        moved += model.n_points - int(np.count_nonzero(deformation.fixed))
        wants.append(chunk_wants(model, deformation, fld.delta_c, a))
    return decide(wants, moved)


def field_children(fld, model, out, start: int, stop: int, decision: Decision,
                   backend: str | None, emit: Callable) -> None:
    """:func:`chunk_children` of the chunk [start, stop) of a streamed field ``apply``."""
    rows, counts = decision.within(start, stop)
    if rows.size:
        chunk_children(model, out, fld.deformation(model, backend), fld.delta_c, rows, counts,
                       fld.meta.get("gaussians", {}).get("covariance", "jacobian"), emit)
