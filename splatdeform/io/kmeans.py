"""Seeded, deterministic k-means for the SOG codebooks (numpy/scipy only).

``codebook_1d``: the SOG codebooks (log scales, colours, SH values): the whole range covered.
A histogram of at most 1024 bins over the finite values (bin edges a blend of value-space and
rank-space positions, more rank-space the heavier the tails), then the optimal partition of the
bins into k cells by dynamic programming, each bin weighted by the square root of its count so
that sparse tails get cells of their own (the method of splat-transform 3.7.0's codebooks,
learned from its documented source; our own code, the DP vectorised row by row), then Lloyd
iterations on the values themselves, kept only while the largest error stays within 1.1x of
the DP's. +-inf values get an end entry 20 beyond the finite range (as splat-transform).
``kmeans_1d``: exact Lloyd iterations on sorted scalars (each step is a search of the cell
boundaries in the sorted data and prefix sums: O(k log N)), started from ``init`` centres or
the data's quantiles.
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
              fill: np.ndarray | None = None, iterations: int = 30,
              init: np.ndarray | None = None) -> np.ndarray:
    """(k,) float32 sorted centres of the (M,) values ``data``; ``fixed`` (F,) centres stay
    as they are (F <= k). With no data, the free centres come from ``fill`` (or repeat).
    ``init``: the free centres to start from (k - F values; default the data's quantiles)."""
    fixed = np.zeros(0) if fixed is None else np.unique(np.asarray(fixed, dtype=np.float64))
    free = k - len(fixed)
    x = np.sort(np.asarray(data, dtype=np.float64).ravel())
    if free <= 0:
        return _pad(fixed[:k], k)
    if len(x) == 0:
        x = np.sort(np.asarray(fill if fill is not None else np.zeros(1), np.float64).ravel())
        if len(x) == 0:
            x = np.zeros(1)
    centres = np.quantile(x, (np.arange(free) + 0.5) / free) if init is None or \
        len(init) != free else np.sort(np.asarray(init, dtype=np.float64))
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


HIST_BINS = 1024
INF_MARGIN = 20.0      # where an end entry for +-inf values sits beyond the finite range
MAX_ERROR_GROWTH = 1.1  # Lloyd refinement kept while the largest error stays within this


def _histogram(x: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """(B,) bin means and counts of the sorted finite values ``x`` (empty bins dropped)."""
    n = len(x)
    span = x[-1] - x[0]
    iqr = x[int(n * 0.75)] - x[int(n * 0.25)]
    beta = max(0.5, min(0.999, 1.0 - iqr / span))
    pos = beta * (np.arange(n) / n) + (1.0 - beta) * (x - x[0]) / span
    b = np.minimum(bins - 1, np.floor(bins * pos).astype(np.int64))
    counts = np.bincount(b, minlength=bins).astype(np.float64)
    sums = np.bincount(b, weights=x, minlength=bins)
    keep = counts > 0
    return sums[keep] / counts[keep], counts[keep]


def _optimal_cells(centres: np.ndarray, weights: np.ndarray, k: int) -> np.ndarray:
    """(k',) the weighted means of the optimal partition of the sorted (B,) ``centres`` into
    k' = min(k, B) contiguous cells (least weighted squared error), by dynamic programming:
    row j of the (B, B) cost table holds every split s < j, so each of the k' steps is one
    add and one argmin along rows."""
    b = len(centres)
    k = min(k, b)
    pw = np.concatenate([[0.0], np.cumsum(weights)])
    pwx = np.concatenate([[0.0], np.cumsum(weights * centres)])
    pwxx = np.concatenate([[0.0], np.cumsum(weights * centres * centres)])
    j = np.arange(b)[:, None]
    s = np.arange(b)[None, :]
    w = pw[j + 1] - pw[s + 1]
    wx = pwx[j + 1] - pwx[s + 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = np.where(w > 0, (pwxx[j + 1] - pwxx[s + 1]) - wx * wx / np.where(w > 0, w, 1),
                        0.0)
    cost[s >= j] = np.inf             # cost[j, s]: one cell over bins s+1 .. j
    del w, wx
    best = pwxx[1:] - pwx[1:] ** 2 / pw[1:]   # one cell over bins 0 .. j
    splits = np.zeros((k + 1, b), dtype=np.int32)
    table = np.empty_like(cost)
    rows = np.arange(b)
    for m in range(2, k + 1):
        np.add(cost, best[None, :], out=table)
        table[:, :m - 2] = np.inf
        split = np.argmin(table, axis=1)
        best = table[rows, split]
        splits[m] = split
    out = np.empty(k)
    end = b - 1
    for m in range(k, 0, -1):
        start = splits[m][end] + 1 if m > 1 else 0
        out[m - 1] = (pwx[end + 1] - pwx[start]) / (pw[end + 1] - pw[start])
        end = start - 1
    return np.sort(out)


def _worst(book: np.ndarray, x: np.ndarray) -> float:
    """Largest distance from a value of sorted ``x`` to its nearest entry of sorted ``book``."""
    at = np.clip(np.searchsorted(book, x), 1, len(book) - 1)
    return float(np.minimum(np.abs(x - book[at - 1]), np.abs(x - book[at])).max())


def codebook_1d(data: np.ndarray, k: int, *, fixed: np.ndarray | None = None,
                fill: np.ndarray | None = None, iterations: int = 10) -> np.ndarray:
    """(k,) float32 sorted codebook of the values ``data`` covering their whole range (the
    module's docstring); ``fixed`` (F,) entries are kept as they are (a re-write), the others
    fitted to ``data``; with no data they come from ``fill``."""
    values = np.asarray(data, dtype=np.float64).ravel()
    if not len(values) and fill is not None:
        values = np.asarray(fill, dtype=np.float64).ravel()
    ends = [v for v in (-np.inf, np.inf) if (values == v).any()]
    x = np.sort(values[np.isfinite(values)])
    free = k - (0 if fixed is None else len(np.unique(fixed)))
    if free <= 0 or len(x) == 0 or x[-1] - x[0] < 1e-20 or free - len(ends) < 1:
        return kmeans_1d(np.clip(values, -3e38, 3e38) if len(values) else values, k,
                         fixed=fixed, fill=fill, iterations=iterations)
    sentinels = [x[0] - INF_MARGIN if v < 0 else x[-1] + INF_MARGIN for v in ends]
    centres, counts = _histogram(x, min(HIST_BINS, len(x)))
    cells = _optimal_cells(centres, np.sqrt(counts), free - len(ends))
    fixed_all = np.concatenate([np.zeros(0) if fixed is None else
                                np.asarray(fixed, np.float64), sentinels])
    base = _pad(np.sort(np.concatenate([fixed_all, cells])), k).astype(np.float64)
    if len(cells) < free - len(ends):   # fewer distinct values than entries: every one exact
        return base.astype(np.float32)
    refined = kmeans_1d(x, k, fixed=fixed_all if len(fixed_all) else None,
                        iterations=iterations, init=cells).astype(np.float64)
    if _worst(refined, x) <= MAX_ERROR_GROWTH * _worst(base, x):
        return refined.astype(np.float32)
    return base.astype(np.float32)
