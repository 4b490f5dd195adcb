"""Seeded, deterministic k-means for the SOG codebooks (numpy/scipy only).

``kmeans_1d``: exact Lloyd iterations on sorted scalars (each step is a search of the cell
boundaries in the sorted data and prefix sums: O(k log N)), started from the data's quantiles.
``kmeans_rows``: Lloyd on vectors (the SH palette), started from distinct rows drawn by a seeded
generator (every distinct row is a centre when there are no more of them than centres), trained
on a seeded sample of at most ``SAMPLE_PER_CENTRE`` rows per centre, then every row assigned to
its nearest centre in blocks. Both accept ``fixed`` centres that are used but
never moved (a re-write keeps the entries its untouched splats use).
"""

from __future__ import annotations

import numpy as np

SAMPLE_PER_CENTRE = 16
BLOCK_VALUES = 1 << 22  # distances held at a time by nearest_rows (16 MiB of float32)


def kmeans_1d(data: np.ndarray, k: int, *, fixed: np.ndarray | None = None,
              fill: np.ndarray | None = None, iterations: int = 30) -> np.ndarray:
    """(k,) float32 sorted centres of the (M,) values ``data``; ``fixed`` (F,) centres stay
    as they are (F <= k). With no data, the free centres come from ``fill`` (or repeat)."""
    fixed = np.zeros(0) if fixed is None else np.unique(np.asarray(fixed, dtype=np.float64))
    free = k - len(fixed)
    x = np.sort(np.asarray(data, dtype=np.float64).ravel())
    if free <= 0:
        return _pad(fixed[:k], k)
    if len(x) == 0:
        x = np.sort(np.asarray(fill if fill is not None else np.zeros(1), np.float64).ravel())
        if len(x) == 0:
            x = np.zeros(1)
    centres = np.quantile(x, (np.arange(free) + 0.5) / free)
    prefix = np.concatenate([[0.0], np.cumsum(x)])
    for _ in range(iterations):
        allc = np.concatenate([fixed, centres])
        is_free = np.concatenate([np.zeros(len(fixed), bool), np.ones(free, bool)])
        order = np.argsort(allc, kind="stable")
        allc, is_free = allc[order], is_free[order]
        cuts = np.searchsorted(x, (allc[1:] + allc[:-1]) / 2)
        starts = np.concatenate([[0], cuts])
        ends = np.concatenate([cuts, [len(x)]])
        counts = ends - starts
        means = np.where(counts > 0, (prefix[ends] - prefix[starts]) / np.maximum(counts, 1),
                         allc)
        new = np.where(is_free, means, allc)
        moved = not np.array_equal(new[is_free], np.sort(centres))
        centres = new[is_free]
        if not moved:
            break
    return _pad(np.sort(np.concatenate([fixed, centres])), k)


def _pad(centres: np.ndarray, k: int) -> np.ndarray:
    out = np.full(k, centres[-1] if len(centres) else 0.0)
    out[:len(centres)] = centres
    return np.sort(out).astype(np.float32)


def _flat(rows: np.ndarray) -> np.ndarray:
    """(M, ...) -> (M, D) (a copy only when ``rows`` is a strided view)."""
    return rows.reshape(len(rows), -1)


def nearest_rows(rows: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(M,) int64 index of the nearest of (C, D) ``centres`` for each of (M, D) ``rows`` (or
    (M, ...) rows of D values: a strided view is flattened one block at a time)."""
    rows = np.asarray(rows, dtype=np.float32)
    c = np.asarray(centres, dtype=np.float32)
    norms = (c * c).sum(axis=1)
    out = np.empty(len(rows), dtype=np.int64)
    step = max(256, BLOCK_VALUES // max(len(c), 1))  # rows per block: one bounded matrix
    for at in range(0, len(rows), step):
        dist = _flat(rows[at:at + step]) @ c.T
        dist *= np.float32(-2)
        dist += norms
        out[at:at + step] = np.argmin(dist, axis=1)
    return out


def kmeans_rows(rows: np.ndarray, k: int, *, fixed: np.ndarray | None = None,
                iterations: int = 10, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(C, D) float32 centres (``fixed`` first, C <= k) and (M,) labels of (M, D) ``rows`` (or
    (M, ...) rows of D values, e.g. a transposed view: never copied whole)."""
    from scipy import sparse

    rows = np.asarray(rows, dtype=np.float32)
    d = int(np.prod(rows.shape[1:]))
    fixed = np.zeros((0, d), np.float32) if fixed is None else np.asarray(fixed, np.float32)
    rng = np.random.default_rng(seed)
    m = len(rows)
    free = max(0, min(k - len(fixed), m))
    if free == 0:
        centres = fixed if len(fixed) else np.zeros((1, d), np.float32)
        return centres, nearest_rows(rows, centres) if m else np.zeros(0, np.int64)
    train = _flat(rows if m <= SAMPLE_PER_CENTRE * free else
                  rows[np.sort(rng.choice(m, SAMPLE_PER_CENTRE * free, replace=False))])
    distinct = np.unique(train, axis=0)
    if len(distinct) <= free:  # as many centres as distinct rows: every row is exact
        centres = np.concatenate([fixed, distinct]).astype(np.float32)
        return centres, nearest_rows(rows, centres)
    moving = distinct[np.sort(rng.choice(len(distinct), free, replace=False))].copy()
    n_fixed = len(fixed)
    for _ in range(iterations):
        centres = np.concatenate([fixed, moving])
        labels = nearest_rows(train, centres)
        member = sparse.csr_matrix((np.ones(len(train), np.float32),
                                    (labels, np.arange(len(train)))),
                                   shape=(len(centres), len(train)))
        sums = np.asarray(member @ train)
        counts = np.asarray(member.sum(axis=1)).ravel()
        grown = counts[n_fixed:] > 0
        moving[grown] = sums[n_fixed:][grown] / counts[n_fixed:][grown, None]
    centres = np.concatenate([fixed, moving]).astype(np.float32)
    return centres, nearest_rows(rows, centres)
