"""Cubic voxel cells over a point set, and exact k-nearest-neighbour queries that build a kd-tree
over the points near the queries only (the rings' border band), not over the whole model.

Cells: ``ijk = floor((p - lo) / edge) + 1`` (1-based, so every occupied cell has its 26
neighbours inside the grid), keyed ``ijk . strides``. When the grid is small enough (at most a
few bytes per point) the keys index dense arrays directly, with no sort at all; otherwise the
occupied keys are sorted once (``np.unique``) and neighbours found by binary search.

Exactness of a query against the subset tree: a point whose cell lies ``L`` cells inside the
subset's cells has every point within ``L * edge`` of it in the subset, so its neighbours are
the whole model's when the (k+1)-th lies within that distance. When the (k+1)-th and (k+2)-th
distances tie, which of the tied points a kd-tree returns depends on the tree's shape; such
queries (and any not certified) go to the whole-model tree, built only then, so the result is
always what ``cKDTree(positions)`` gives.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from splatdeform.geometry import bounds
from splatdeform.interrupts import knn_query

#: Dense cell arrays (a byte or a bool per cell) when the grid has at most this many cells
#: per point (or 4M cells).
_DENSE_PER_POINT = 8
_DENSE_MIN = 1 << 22
_BLOCK = 1 << 16
_OFFSETS = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                     if (i, j, k) != (0, 0, 0)], dtype=np.int64)
#: Certified distances stay this far inside the cells (float rounding of the cell of a point).
_MARGIN = 1 - 1e-9
_BLOCK27 = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)],
                    dtype=np.int64)
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


def _grid(edge: float, box: tuple) -> tuple[np.ndarray, np.ndarray, float]:
    """(lo (3,), strides (3,) int64, number of cells) of the grid of edge ``edge`` over the
    box (lo, hi); floor is monotone, so the largest ijk is the box corner's."""
    lo, hi = box
    dims = np.floor((hi - lo) / edge).astype(np.int64) + 3
    total = float(np.prod(dims.astype(np.float64)))
    if not total < 2.0**52:
        raise GridTooFine(f"cells of {edge:.3g} over a box of {hi - lo}")
    return lo, np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64), total


def _blocks(positions: np.ndarray, lo: np.ndarray, edge: float, strides: np.ndarray):
    """(start, keys (M,) float64) for each cache-sized block of points: the integer keys
    ``(floor((p - lo) / edge) + 1) . strides``, exact in float64 below 2**52, computed in
    place."""
    n = positions.shape[0]
    buf = np.empty((min(_BLOCK, n), 3))
    s0, s1, s2 = (float(v) for v in strides)
    base = s0 + s1 + s2  # the + 1 of every axis, added once (exact integers below 2**52)
    for a in range(0, n, _BLOCK):
        w = buf[:min(_BLOCK, n - a)]
        np.subtract(positions[a:a + _BLOCK], lo, out=w)
        np.divide(w, edge, out=w)
        np.floor(w, out=w)
        key = w[:, 0] * s0
        key += w[:, 1] * s1
        key += w[:, 2] * s2 if s2 != 1 else w[:, 2]
        key += base
        yield a, key


def cell_keys(positions: np.ndarray, edge: float, box: tuple | None = None
              ) -> tuple[np.ndarray, np.ndarray, float]:
    """(keys (N,), strides (3,) int64, number of cells in the grid) of the cells of edge
    ``edge`` holding points (N, 3): ``(floor((p - lo) / edge) + 1) . strides``; ``box`` the
    points' (lo, hi) when known. Keys are int32 when the grid allows (half the memory)."""
    lo, strides, total = _grid(edge, bounds(positions) if box is None else box)
    keys = np.empty(positions.shape[0], dtype=np.int32 if total < 2**31 else np.int64)
    for a, block in _blocks(positions, lo, edge, strides):
        keys[a:a + block.size] = block
    return keys, strides, total


def _points_in(positions: np.ndarray, edge: float, box: tuple, table: np.ndarray
               ) -> np.ndarray:
    """(M,) int64 indices of the points (N, 3) whose cell (of edge ``edge`` over ``box``) is
    one of the keys ``table``, a block at a time (no N-long key array): a bitmap of the grid
    (total / 8 bytes) when it is small, else a binary search."""
    lo, strides, total = _grid(edge, box)
    n = positions.shape[0]
    table = np.unique(table)
    bitmap = None
    if total <= 64 * n + (1 << 25):
        bitmap = np.zeros(int(total) // 8 + 1, dtype=np.uint8)
        np.bitwise_or.at(bitmap, table >> 3, (1 << (table & 7)).astype(np.uint8))
    found = []
    for a, block in _blocks(positions, lo, edge, strides):
        keys = block.astype(np.int64)
        if bitmap is not None:
            hit = (bitmap[keys >> 3] >> (keys & 7).astype(np.uint8)) & 1
        else:
            at = np.minimum(np.searchsorted(table, keys), table.size - 1)
            hit = table[at] == keys
        found.append(np.flatnonzero(hit) + a)
    return np.concatenate(found) if found else np.empty(0, dtype=np.int64)


class GridTooFine(ValueError):
    """The cells would number 2**52 or more (keys no longer exact)."""


class Cells:
    """Points (N, 3) hashed into cells of edge ``edge``.

    ``cell`` (N,) int64: each point's cell id in [0, size); cell arrays have ``size + 1``
    entries, the last one standing for "no such cell" (a neighbour outside the occupied set in
    the sorted layout). ``occupied`` (C,) int64: the ids of cells holding points.
    """

    def __init__(self, positions: np.ndarray, edge: float, box: tuple | None = None) -> None:
        n = positions.shape[0]
        self.edge = float(edge)
        keys, self.strides, total = cell_keys(positions, edge, box)
        self.dense = total <= max(_DENSE_PER_POINT * n, _DENSE_MIN)
        if self.dense:
            self.size = int(total)
            self.cell = keys
            used = np.zeros(self.size + 1, dtype=bool)
            used[keys] = True
            self.occupied = np.flatnonzero(used)
            self.keys = None
        else:
            uniq, inverse = np.unique(keys, return_inverse=True)
            self.size = int(uniq.size)
            self.cell = inverse.reshape(-1)
            self.occupied = np.arange(self.size)
            self.keys = uniq.astype(np.int64)

    def shift(self, ids: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """The cells at ``offset`` (3,) ints from cells ``ids`` (M,): ids, or ``size`` where the
        sorted layout has no such cell."""
        step = int(offset @ self.strides)
        if self.dense:
            return ids + step
        want = self.keys[ids] + step
        pos = np.minimum(np.searchsorted(self.keys, want), self.size - 1)
        return np.where(self.keys[pos] == want, pos, self.size)

    def dilate(self, mask: np.ndarray) -> np.ndarray:
        """(size + 1,) bool: occupied cells of ``mask`` or next to one (26-neighbourhood)."""
        out = mask.copy()
        occ = self.occupied[~mask[self.occupied]]
        hit = np.zeros(occ.size, dtype=bool)
        for off in _OFFSETS:
            hit |= mask[self.shift(occ, off)]
        out[occ[hit]] = True
        return out

    def label_border(self, labels: np.ndarray) -> np.ndarray:
        """(size + 1,) bool: occupied cells whose 3x3x3 block holds two or more labels
        (labels (N,) small non-negative ints, at most 8 distinct values used as bits)."""
        flags = np.zeros(self.size + 1, dtype=np.uint8)
        lab = labels.ravel()
        low, high = (int(lab.min()), int(lab.max())) if lab.size else (0, -1)
        if low >= 0 and high < 8:  # each point's bit OR-ed into its cell in one pass
            np.bitwise_or.at(flags, self.cell, np.uint8(1) << lab.astype(np.uint8))
        else:
            for label in np.unique(lab):  # an absent label sets no bit
                flags[self.cell[lab == label]] |= np.uint8(1 << int(label))
        occ = self.occupied
        around = flags[occ]
        for off in _OFFSETS:
            around |= flags[self.shift(occ, off)]
        border = np.zeros(self.size + 1, dtype=bool)
        border[occ] = _POPCOUNT[around] >= 2
        return border


class SubsetKnn:
    """Exact kNN (as ``cKDTree(positions).query``) for queries near a set of cells.

    ``levels`` (size + 1,) int8 from :func:`levels_around`: 0 for the core cells, l for cells l
    steps away, -1 beyond; the subset is every point of a cell with a level >= 0.
    """

    def __init__(self, positions: np.ndarray, cells: Cells, levels: np.ndarray,
                 reach: int) -> None:
        self.positions = positions
        self.cells = cells
        self.levels = levels
        self.reach = reach
        self.subset = np.flatnonzero(levels[cells.cell] >= 0)
        self.tree: cKDTree | None = None   # built at the first query
        self.whole: cKDTree | None = None
        self.queried = 0       # points queried (work counts, for the tests and benchmarks)
        self.fallback = 0      # of those, answered by the whole-model tree

    def query(self, idx: np.ndarray, k1: int) -> np.ndarray:
        """(Q, k1) int64 neighbour indices of points ``idx`` (Q,), the same sets as the
        whole-model tree's ``query(k=k1)``."""
        n = self.positions.shape[0]
        pts = self.positions[idx]
        self.queried += idx.size
        m = self.subset.size
        level = self.levels[self.cells.cell[idx]].astype(np.float64)
        safe = np.where(level >= 0, (self.reach - level) * self.cells.edge * _MARGIN, -1.0)
        if m >= k1 + 1:
            if self.tree is None:
                self.tree = cKDTree(self.positions[self.subset])
            dist, local = knn_query(self.tree, pts, k=k1 + 1)
            nbr = np.where(local < m, self.subset[np.minimum(local, m - 1)], n)[:, :k1]
            ok = (dist[:, k1 - 1] <= safe) & (dist[:, k1 - 1] < dist[:, k1])
        else:
            nbr = np.full((idx.size, k1), n, dtype=np.int64)
            ok = np.zeros(idx.size, dtype=bool)
        if not ok.all():
            bad = np.flatnonzero(~ok)
            self.fallback += bad.size
            if self.whole is None:
                self.whole = cKDTree(self.positions)
            nbr[bad] = knn_query(self.whole, pts[bad], k=k1)[1]
        return nbr


def levels_around(cells: Cells, core: np.ndarray, reach: int) -> np.ndarray:
    """(size + 1,) int8: 0 on the ``core`` cells (size + 1,) bool, l on the occupied cells l
    26-neighbourhood steps away (l <= reach), -1 elsewhere."""
    levels = np.full(cells.size + 1, -1, dtype=np.int8)
    levels[core] = 0
    levels[-1] = -1
    inside = core.copy()
    inside[-1] = False
    for step in range(1, reach + 1):
        grown = cells.dilate(inside)
        grown[-1] = False
        levels[grown & ~inside] = step
        inside = grown
    return levels


def kth_distances(positions: np.ndarray, idx: np.ndarray, k1: int, guess: float,
                  attempts: int = 4, max_share: float = 0.25, box: tuple | None = None
                  ) -> tuple[np.ndarray, cKDTree | None]:
    """(Q,) exact distance of points ``idx`` (Q,) to their ``k1``-th nearest point (themselves
    counted), from kd-trees over the cells around them: cells of edge ``guess`` first, doubled
    for the points not yet certified. The whole model's tree answers the rest after
    ``attempts``, or at once when the cells around the queries hold more than ``max_share``
    of the points; it is returned (else None) for the caller to reuse."""
    out = np.full(idx.size, np.nan)
    todo = np.arange(idx.size)
    edge = guess
    n = positions.shape[0]
    box = bounds(positions) if box is None else box
    for _ in range(attempts if idx.size * 32 < max_share * n else 0):
        if todo.size == 0 or not edge > 0:
            break
        try:
            lo, strides, _ = _grid(edge, box)
        except GridTooFine:
            break
        own = np.concatenate([b for _, b in _blocks(positions[idx[todo]], lo, edge, strides)]
                             ).astype(np.int64)
        subset = _points_in(positions, edge, box,
                            (own[:, None] + (_BLOCK27 @ strides)[None, :]).ravel())
        if subset.size > max_share * n or subset.size < k1:
            break
        dist = knn_query(cKDTree(positions[subset]), positions[idx[todo]], k=k1)[0][:, -1]
        ok = dist <= edge * _MARGIN
        out[todo[ok]] = dist[ok]
        todo = todo[~ok]
        edge *= 2
    whole = None
    if todo.size:
        whole = cKDTree(positions)
        out[todo] = knn_query(whole, positions[idx[todo]], k=k1)[0][:, -1]
    return out, whole
