"""The order the SOG writer stores splats in: Morton (Z-order) by default, or the input's.

Renderers sort splats by depth every frame, so the stored order carries no meaning; neighbours in
space next to each other in the images make the lossless WebP images much smaller (measured: a
150k-splat scene stored in random order, 1.14x splat-transform's file kept in that order, 1.00x
in Morton order). splat-transform 3.7.0 writes SOG in this order, computed the same way (10 bits
per axis over the float32 positions' bounding box, equal codes kept in their input order, a run
of more than 256 equal codes sorted again over its own box), so both tools order a scene alike.
``keep`` writes the splats in their given order.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

import numpy as np

from ..errors import InputError
from .splats import SplatFields

ORDERS = ("morton", "keep")
_ORDER: ContextVar[str] = ContextVar("sog_order", default="morton")
BITS = 10            # per axis and level: a 30-bit code
REFINE = 256         # a run of more equal codes is ordered again inside its own box


@contextmanager
def order(name: str | None) -> Iterator[None]:
    """SOG writes inside the block store splats in order ``name`` (one of :data:`ORDERS`;
    None: the default, ``morton``)."""
    if name is not None and name not in ORDERS:
        raise InputError(f"sog_order: expected one of {', '.join(ORDERS)}, got {name!r}")
    token = _ORDER.set(name or "morton")
    try:
        yield
    finally:
        _ORDER.reset(token)


def current() -> str:
    """The order in force (:func:`order`)."""
    return _ORDER.get()


def _spread(v: np.ndarray) -> np.ndarray:
    """(M,) uint32 of 10-bit values -> their bits spread to every third bit."""
    v = v & np.uint32(0x3FF)
    v = (v ^ (v << np.uint32(16))) & np.uint32(0xFF0000FF)
    v = (v ^ (v << np.uint32(8))) & np.uint32(0x0300F00F)
    v = (v ^ (v << np.uint32(4))) & np.uint32(0x030C30C3)
    return (v ^ (v << np.uint32(2))) & np.uint32(0x09249249)


def _codes(p: np.ndarray) -> np.ndarray | None:
    """(M,) uint32 Morton codes of (M, 3) float64 points in their bounding box; None when the
    box is not finite or is a single point (the run keeps its order)."""
    lo, hi = p.min(axis=0), p.max(axis=0)
    span = hi - lo
    if not np.isfinite(span).all() or not span.any():
        return None
    scale = np.divide(1 << BITS, span, out=np.zeros(3), where=span > 0)
    cell = np.minimum((1 << BITS) - 1, (p - lo) * scale).astype(np.uint32)
    return (_spread(cell[:, 2]) << np.uint32(2)) + (_spread(cell[:, 1]) << np.uint32(1)) + \
        _spread(cell[:, 0])


def morton_order(positions: np.ndarray) -> np.ndarray:
    """(N,) int64 permutation putting (N, 3) ``positions`` in Morton order: ``positions[out]``
    is sorted. Computed on the positions rounded to float32 (what SOG's writers read), as
    splat-transform 3.7.0 orders them."""
    with np.errstate(over="ignore", invalid="ignore"):   # past float32: no order (refused later)
        p = np.asarray(positions, dtype=np.float64).astype(np.float32).astype(np.float64)
    out = np.arange(len(p), dtype=np.int64)
    # a box that is not finite: the input's order (splat-transform's rule, and any run inside a
    # finite box has a finite box)
    runs = [(0, len(p))] if len(p) > 1 and np.isfinite(p).all() else []
    while runs:
        start, end = runs.pop()
        rows = out[start:end]
        codes = _codes(p[rows])
        if codes is None:
            continue
        by = np.argsort(codes, kind="stable")
        out[start:end] = rows[by]
        codes = codes[by]
        edges = np.concatenate([[0], np.flatnonzero(np.diff(codes)) + 1, [len(codes)]])
        long = np.flatnonzero(np.diff(edges) > REFINE)
        runs.extend((start + int(edges[i]), start + int(edges[i + 1])) for i in long)
    return out


def take(fields: SplatFields, rows: np.ndarray) -> SplatFields:
    """The splats ``rows`` ((M,) indices) of ``fields``, in that order."""
    from dataclasses import fields as columns
    from dataclasses import replace

    return replace(fields, **{c.name: getattr(fields, c.name)[rows] for c in columns(fields)})
