"""``fit.method: auto``: the cheapest of the incremental fit (on the kept constraints), the
dense exact solve through the kept constraints, and the dense exact solve through every
constraint, by predicted cost, checked over every ring point.

The dense solve's cost is known before it starts: one Cholesky of about m^3 / 3 flops on its
threads (:func:`splatdeform.rbf.exact.dense_threads`), plus building the m x m kernel
matrix. Through the m_kept thinned constraints it costs m_kept^3 / 3 plus one evaluation at
every ring point (the boundary check). The incremental fit's cost grows with the centers it
needs, which are only known as it goes: about 2 m_kept n^2 flops of blocked Householder QR on
one thread, at several times less flops per second than the Cholesky, plus per-center and
per-block overheads. On thick noisy rings it needs a center for most kept points, where the
dense solve through the kept points is many times cheaper. So ``auto``

1. solves densely through every point at once when that is predicted to take at most
   :data:`TINY_DENSE` seconds (nothing to win); else densely at once (through the kept points
   when that is predicted cheaper than through all, method "exact-kept"; else "exact") when
   the solve through every point is predicted to take at most :data:`SMALL_DENSE` seconds
   (small scenes: little to win), or when even the incremental fit's first blocks are
   predicted to cost more;
2. else runs the incremental fit and, after each block, stops and switches to the cheaper dense
   solve once its predicted cost so far has passed that dense cost, or once the centers it is
   heading for (log-linear extrapolation of the largest |r| from a third of its centers to now,
   down to the tolerance, the remaining centers times :data:`HEADING_FACTOR`) predict a
   remaining cost above it at two checks in a row (or :data:`FAR_PAST` times above it at one;
   at the first check, :data:`FIRST_CENTERS` centers, only :data:`EARLY_FAR` times above it);
3. also switches when the incremental fit stops at ``max_centers`` above the tolerance, so every
   scene the dense solve can take converges;
4. and when the incremental fit met the tolerance on the kept constraints but misses a dropped
   ring point by more than :data:`BOUNDARY_FACTOR` times the tolerance (|r| over the dropped ring
   point, one cheap evaluation): thinning is only used where it keeps the boundary.

A dense solve through the kept points is checked the same way; the dropped ring points it
misses by more than :data:`BOUNDARY_FACTOR` tolerances join the kept set and it is solved again
(the fit's ``kept`` says which points it went through), as long as the predicted costs of
these retries stay below :data:`DENSE_KEPT_SHARE` of the dense solve through every point,
which runs otherwise.

The constants are from ``benchmarks/fit_table.py`` on the development machine
(docs/benchmarks.md, "The table behind the defaults"); they are costs in seconds on one core,
only their ratios matter. Decisions use the counts alone, never wall time nor the thread count
(costs are predicted for one thread), so the same scene gets the same fit on every machine and
thread setting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from splatdeform.errors import InputError
from splatdeform.rbf.defaults import DEFAULT_MAX_CENTERS, DEFAULT_TOLERANCE
from splatdeform.rbf.exact import (
    EXACT_MAX_CONSTRAINTS,
    dense_threads,
    distinct_rows,
    fit_exact,
)
from splatdeform.rbf.fit import blas_threads, fit_incremental
from splatdeform.rbf.kernel import cubed_distance_rows
from splatdeform.rbf.result import Normalization, RbfFit

#: Flop rate of one thread in the dense Cholesky (BLAS-3, large blocks; ~40-50 measured).
DENSE_FLOPS = 40e9
#: Parallel efficiency exponent: t threads run ``t ** DENSE_SCALING`` times faster.
DENSE_SCALING = 0.8
#: Seconds per kernel-matrix entry (the blocked build of one triangle, Phi V, the rank-8
#: update, the solve).
DENSE_ENTRY = 5e-9
#: Seconds per (dropped ring point x center) of the boundary check of a thinned fit (the kept
#: points are met by the fit itself: a dense solve interpolates them, the incremental fit
#: meets the tolerance there).
CHECK_ENTRY = 3e-9  # 2.6e-9 measured with the blocked kernel values (7e-9 with cdist)
#: Effective flop rate of the incremental fit's blocked QR on its one thread. The three
#: incremental constants are a least-squares fit (relative error) to the incremental fits of
#: ten scenes of ``benchmarks/fit_table.py`` (218-1,277 centers, 279-4,136 constraints): within
#: -28% .. +20% of each measured time (the last constants over-predicted by 1.1-1.9x).
INCREMENTAL_FLOPS = 15e9
#: Seconds per (kept constraint x center) for the picks, kernel columns and residual checks.
INCREMENTAL_ENTRY = 1.1e-8
#: Seconds of fixed cost per center block (Python, LAPACK calls, the residual recovery).
INCREMENTAL_BLOCK = 0.8e-3
#: Predicted seconds below which a dense solve runs at once (m up to about 1,500 on one
#: thread): the cheaper of the solve through every point and through the kept points.
SMALL_DENSE = 0.04
#: Predicted seconds below which the solve through every point runs at once (m up to about
#: 800): a few milliseconds, about the cost of one thinned solve and its boundary check.
TINY_DENSE = 0.006
#: Centers of the first blocks (16 + 32 + 64): the least work an incremental fit does.
FIRST_CENTERS = 112
#: Centers before the extrapolated heading is trusted (first checked at 176 centers; at 112 it
#: was -49% .. +178% off the final count on the scenes of ``benchmarks/fit_table.py`` and
#: the tests' grid sheet).
HEADING_AFTER = 160
#: The centers still to add, as the log-linear extrapolation predicts them, times this: the
#: largest |r| falls more slowly as the fit goes on (3-7x more slowly from 176 centers to the
#: end than from 112 to 176 on the scenes of ``benchmarks/fit_table.py``); with it the
#: heading at 176 centers was within -20% .. +40% of the final count on every scene.
HEADING_FACTOR = 3.0
#: A heading whose remaining cost passes the dense cost this many times over stops the
#: incremental fit at once (else it takes two checks in a row).
FAR_PAST = 2.0
#: Before :data:`HEADING_AFTER` centers (the check at :data:`FIRST_CENTERS`) the heading
#: stops the fit only when its remaining cost passes the dense cost this many times over.
#: The heading at 112 centers over-predicted the remaining cost by up to 3.5x on the scenes
#: of ``benchmarks/fit_table.py`` and the tests' grid sheet (519 centers predicted, 187
#: needed: 3.4x the dense cost predicted, 0.95x needed), so above 4.5x even the most
#: optimistic reading has the incremental fit lose; the igea mesh (5.6x, 973 centers needed
#: for 2,156 kept points) then goes to the dense solve 64 centers (~6 ms) sooner.
EARLY_FAR = 4.5
#: Largest |r| over every ring point (kept or dropped) that ``auto`` accepts from a thinned
#: incremental fit, in tolerances; above it the dense solve runs (docs/benchmarks.md, the fit
#: table).
BOUNDARY_FACTOR = 10.0


def dense_seconds(m: int, threads: int) -> float:
    """Predicted seconds of the dense exact solve through ``m`` distinct constraints."""
    if m > EXACT_MAX_CONSTRAINTS:
        return math.inf
    return (m ** 3 / 3.0) / (DENSE_FLOPS * max(threads, 1) ** DENSE_SCALING) \
        + DENSE_ENTRY * m * m


def incremental_seconds(m: int, n: int, block: int = 64) -> float:
    """Predicted seconds of the incremental fit with ``n`` centers on ``m`` constraints."""
    n = max(int(n), 0)
    blocks = _blocks(n, block)
    return (2.0 * m * n * n) / INCREMENTAL_FLOPS + INCREMENTAL_ENTRY * m * (n + 4) \
        + INCREMENTAL_BLOCK * (blocks + 1)


def _blocks(n: int, block: int) -> int:
    count, size, done = 0, min(block, 16), 0
    while done < n:
        done += size
        count += 1
        size = min(block, 2 * size)
    return count


def dense_kept_seconds(m_all: int, m_kept: int, threads: int) -> float:
    """Predicted seconds of the dense solve through ``m_kept`` of ``m_all`` constraints and its
    boundary check at the ``m_all - m_kept`` dropped ones."""
    return dense_seconds(m_kept, threads) + CHECK_ENTRY * (m_all - m_kept) * m_kept


@dataclass(frozen=True)
class Choice:
    """The first decision of ``auto``: method ("exact" | "exact-kept" | "incremental") and the
    predictions (seconds) it was made on: dense through all, dense through the kept ones, and
    the incremental fit's first blocks."""

    method: str
    dense: float
    dense_kept: float
    incremental_start: float

    @property
    def target(self) -> float:
        """The cheaper dense solve's predicted seconds."""
        return min(self.dense, self.dense_kept)

    @property
    def dense_method(self) -> str:
        """The cheaper dense solve: "exact-kept" or "exact"."""
        return "exact-kept" if self.dense_kept < self.dense else "exact"


def choose_method(m_all: int, m_kept: int, threads: int) -> Choice:
    """Dense at once when the incremental fit's first blocks on ``m_kept`` constraints are
    predicted to cost more than the cheaper dense solve (through the kept points, or through
    all ``m_all``); else incremental."""
    dense = dense_seconds(m_all, threads)
    kept = dense_kept_seconds(m_all, m_kept, threads) if m_kept < m_all else math.inf
    start = incremental_seconds(m_kept, min(m_kept, FIRST_CENTERS))
    first = Choice("incremental", dense, kept, start)
    if dense <= TINY_DENSE:
        return Choice("exact", dense, kept, start)
    if dense <= SMALL_DENSE:
        return Choice(first.dense_method, dense, kept, start)
    if start >= first.target:
        return Choice(first.dense_method, dense, kept, start)
    return first


def heading_for(history: list[tuple[int, float]], tolerance: float) -> float | None:
    """Centers the fit is heading for: log-linear extrapolation of (centers, largest |r|) from
    the first checkpoint at a third of the current centers or more to the last one, down to
    ``tolerance`` (a window that grows with the fit, so a plateau of a block or two does not
    swing it).
    None: no progress to extrapolate."""
    if len(history) < 2 or tolerance <= 0:
        return None
    n1, e1 = history[-1]
    n0, e0 = next((h for h in history if h[0] >= n1 // 3), history[-2])
    if n0 >= n1:
        n0, e0 = history[-2]
    if not (n1 > n0 and e0 > 0 and e1 > 0 and e1 < e0):
        return None
    if e1 <= tolerance:
        return float(n1)
    slope = (math.log(e0) - math.log(e1)) / (n1 - n0)
    return n1 + HEADING_FACTOR * (math.log(e1) - math.log(tolerance)) / slope


def fit_auto(points: np.ndarray, rhs: np.ndarray, *, kept: np.ndarray | None = None,
             tolerance: float = DEFAULT_TOLERANCE, max_centers: int = DEFAULT_MAX_CENTERS,
             normalization: Normalization | None = None, selection: str = "greedy",
             threads: int | None = None) -> RbfFit:
    """The cheapest of :func:`fit_incremental` on ``points[kept]``, :func:`fit_exact` on the
    kept points (checked at all of them) and :func:`fit_exact` on all ``points`` (m, 3) /
    ``rhs`` (m, k), by predicted cost (module docstring).

    kept: (m,) bool, the thinned constraints (None: all). threads: the dense solve's BLAS
    threads (None: :func:`dense_threads`); the incremental fit uses one. The returned fit's
    ``method`` says which ran, its ``kept`` the constraints an "exact-kept" solve went through
    when it added missed ones.
    """
    pts = np.asarray(points)
    b = np.asarray(rhs)
    if kept is not None and bool(np.all(kept)):
        kept = None
    sub_p, sub_b = (pts, b) if kept is None else (pts[kept], b[kept])
    m_all = int(distinct_rows(np.asarray(pts, dtype=np.float64))[0].size) \
        if pts.ndim == 2 and pts.shape[0] else 0
    m_kept = m_all if kept is None else int(sub_p.shape[0])
    n_threads = dense_threads(threads)
    # predicted on one thread whatever the solve gets: the same scene gets the same fit under
    # any thread setting (Dask workers and CI set OMP_NUM_THREADS=1)
    choice = choose_method(m_all, m_kept, 1)
    tol = float(tolerance)

    def dense(method: str, fallback: RbfFit | None = None) -> RbfFit:
        return _dense(pts, b, kept if method == "exact-kept" else None, tol,
                      choice.dense, normalization, n_threads, fallback)

    if choice.method != "incremental":
        return dense(choice.method)
    history: list[tuple[int, float]] = []
    over = [False]  # the heading passed the dense cost at the previous check

    def stop(n: int, err: float) -> bool:
        history.append((n, err))
        spent = incremental_seconds(m_kept, n)
        if spent >= choice.target:
            return True
        heading = heading_for(history, tol) if n >= FIRST_CENTERS else None
        left = math.inf if heading is None else \
            incremental_seconds(m_kept, min(heading, 1e9)) - spent
        if n < HEADING_AFTER:  # an early heading: only a hopeless one stops the fit
            return heading is not None and left > EARLY_FAR * choice.target
        passed = heading is not None and left > choice.target
        # twice in a row (not one plateau), or once by far
        give_up = passed and (over[0] or left > FAR_PAST * choice.target)
        over[0] = passed
        return give_up

    try:
        fit = fit_incremental(sub_p, sub_b, tolerance=tolerance, max_centers=max_centers,
                              normalization=normalization, selection=selection, stop=stop)
    except InputError:
        if kept is None or math.isinf(choice.dense):
            raise
        # the kept subset alone is degenerate (e.g. flat): the dense solve takes every point
        return fit_exact(pts, b, normalization=normalization, threads=n_threads)
    if math.isinf(choice.target):
        return fit
    if fit.converged and (kept is None or
                          all_errors(fit, pts[~kept], b[~kept]) <= BOUNDARY_FACTOR * tol):
        return fit
    return dense(choice.dense_method, fit)


#: Most dense solves through a growing kept set before the solve through every point.
DENSE_ROUNDS = 4
#: The kept-set solves stop once their predicted costs pass this share of the solve through
#: every point (the most they can waste before it).
DENSE_KEPT_SHARE = 0.3


def _dense(pts: np.ndarray, b: np.ndarray, kept: np.ndarray | None, tol: float,
           dense_all: float, normalization: Normalization | None, threads: int,
           fallback: RbfFit | None) -> RbfFit:
    """The dense solve through the ``kept`` points (plus the ring points it misses by more than
    :data:`BOUNDARY_FACTOR` tolerances, a few rounds, while the predicted cost stays below
    ``dense_all``), else through every point; ``fallback`` when that is over the limit."""
    if kept is not None:
        mask = np.asarray(kept, dtype=bool).copy()
        m_all, spent = pts.shape[0], 0.0
        for round_ in range(DENSE_ROUNDS):
            count = int(np.count_nonzero(mask))
            if round_:  # the first was chosen as the cheapest: only the retries can waste
                spent += dense_kept_seconds(m_all, count, 1)
                if spent >= DENSE_KEPT_SHARE * dense_all:
                    break  # too many misses: thinning does not keep this boundary
            try:
                fit = fit_exact(pts[mask], b[mask], normalization=normalization,
                                threads=threads)
            except InputError:
                break  # the kept subset alone is degenerate (e.g. flat)
            out = np.flatnonzero(~mask)  # the points it went through it interpolates
            miss = np.zeros_like(mask)
            miss[out] = point_errors(fit, pts[out], b[out]) > BOUNDARY_FACTOR * tol
            if not miss.any():
                return replace(fit, method="exact-kept", tolerance=tol,
                               kept=None if np.array_equal(mask, kept) else mask)
            mask |= miss
    if math.isinf(dense_all) and fallback is not None:
        return fallback
    return fit_exact(pts, b, normalization=normalization, threads=threads)


def all_errors(fit: RbfFit, points: np.ndarray, rhs: np.ndarray) -> float:
    """Largest |rhs - b(points)| of ``fit`` over ``points`` (m, 3) model units, rhs (m, k)."""
    err = point_errors(fit, points, rhs)
    return float(err.max()) if err.size else 0.0


def point_errors(fit: RbfFit, points: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """(m,) largest |rhs - b(p)| over the k columns at each of ``points`` (m, 3) model units,
    rhs (m, k): the kernel values block by block (:func:`cubed_distance_rows`), each times
    the weights while in cache."""
    x = fit.normalization.apply(points)
    val = fit.weights[0] + x @ fit.weights[1:4]
    if fit.n_centers and x.shape[0]:
        w = fit.weights[4:]
        with blas_threads(1):  # k right-hand sides: a thread pool only spins (10x slower busy)
            for a, e, blk in cubed_distance_rows(x, fit.centers):
                val[a:e] += blk @ w
    return np.abs(np.asarray(rhs, dtype=np.float64) - val).max(axis=1)
