"""``fit.method: auto``: the cheaper of the incremental fit (on the kept constraints) and the
dense exact solve (through every constraint), by predicted cost.

The dense solve's cost is known before it starts: one Cholesky of about m^3 / 3 flops on the
BLAS threads (:func:`splatdeform.rbf.exact.dense_threads`), plus building the m x m kernel
matrix. The incremental fit's cost grows with the centers it needs, which are only known as it
goes: about 2 m_kept n^2 flops of blocked Householder QR on one thread, plus per-center and
per-block overheads. So ``auto``

1. solves densely at once when even the incremental fit's first blocks are predicted to cost
   more than the whole dense solve (small scenes);
2. else runs the incremental fit and, after each block, stops and switches to the dense solve
   once its predicted cost so far has passed the dense cost, or once the centers it is heading
   for (log-linear extrapolation of the largest |r| from half its centers to now, down to the
   tolerance) predict a remaining cost above the dense cost at two checks in a row;
3. also switches when the incremental fit stops at ``max_centers`` above the tolerance, so every
   scene the dense solve can take converges;
4. and when the incremental fit met the tolerance on the kept constraints but misses a dropped
   ring point by more than :data:`BOUNDARY_FACTOR` times the tolerance (|r| over every ring
   point, one cheap evaluation): thinning is only used where it keeps the boundary.

The constants are from ``benchmarks/fit_table.py`` (README: "Fit benchmark"); they are costs
in seconds on one core of the development machine, only their ratios matter. Decisions use
the counts alone, never wall time, so they are deterministic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from splatdeform.errors import InputError
from splatdeform.rbf.defaults import DEFAULT_MAX_CENTERS, DEFAULT_TOLERANCE
from splatdeform.rbf.exact import EXACT_MAX_CONSTRAINTS, dense_threads, fit_exact
from splatdeform.rbf.fit import fit_incremental
from splatdeform.rbf.result import Normalization, RbfFit

#: Flop rate of one thread in the dense Cholesky (BLAS-3, large blocks).
DENSE_FLOPS = 15e9
#: Parallel efficiency exponent: t threads run ``t ** DENSE_SCALING`` times faster.
DENSE_SCALING = 0.8
#: Seconds per kernel-matrix entry (cdist, cube, the rank-8 projection).
DENSE_ENTRY = 1.2e-8
#: Effective flop rate of the incremental fit's blocked QR on its one thread.
INCREMENTAL_FLOPS = 3e9
#: Seconds per (kept constraint x center) for the picks, kernel columns and residual checks.
INCREMENTAL_ENTRY = 1.5e-8
#: Seconds of fixed cost per center block (Python, LAPACK calls, the residual recovery).
INCREMENTAL_BLOCK = 2e-3
#: Centers of the first blocks (16 + 32 + 64): the least work an incremental fit does.
FIRST_CENTERS = 112
#: Centers before the extrapolated heading is trusted.
HEADING_AFTER = 128
#: Largest |r| over every ring point (kept or dropped) that ``auto`` accepts from a thinned
#: incremental fit, in tolerances; above it the dense solve runs (README: "Fit benchmark").
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


@dataclass(frozen=True)
class Choice:
    """The first decision of ``auto``: method ("exact" | "incremental") and the predictions
    (seconds) it was made on."""

    method: str
    dense: float
    incremental_start: float


def choose_method(m_all: int, m_kept: int, threads: int) -> Choice:
    """Dense at once when the incremental fit's first blocks on ``m_kept`` constraints are
    predicted to cost more than the dense solve through ``m_all``; else incremental."""
    dense = dense_seconds(m_all, threads)
    start = incremental_seconds(m_kept, min(m_kept, FIRST_CENTERS))
    return Choice("exact" if start >= dense else "incremental", dense, start)


def heading_for(history: list[tuple[int, float]], tolerance: float) -> float | None:
    """Centers the fit is heading for: log-linear extrapolation of (centers, largest |r|) from
    the checkpoint at about half the current centers to the last one, down to ``tolerance``
    (a window that grows with the fit, so a plateau of a block or two does not swing it).
    None: no progress to extrapolate."""
    if len(history) < 2 or tolerance <= 0:
        return None
    n1, e1 = history[-1]
    n0, e0 = next((h for h in history if h[0] >= n1 // 2), history[-2])
    if n0 >= n1:
        n0, e0 = history[-2]
    if not (n1 > n0 and e0 > 0 and e1 > 0 and e1 < e0):
        return None
    if e1 <= tolerance:
        return float(n1)
    slope = (math.log(e0) - math.log(e1)) / (n1 - n0)
    return n1 + (math.log(e1) - math.log(tolerance)) / slope


def fit_auto(points: np.ndarray, rhs: np.ndarray, *, kept: np.ndarray | None = None,
             tolerance: float = DEFAULT_TOLERANCE, max_centers: int = DEFAULT_MAX_CENTERS,
             normalization: Normalization | None = None, selection: str = "greedy",
             threads: int | None = None) -> RbfFit:
    """The cheaper of :func:`fit_incremental` on ``points[kept]`` and :func:`fit_exact` on all
    ``points`` (m, 3) / ``rhs`` (m, k), by predicted cost (module docstring).

    kept: (m,) bool, the constraints the incremental fit uses (None: all). threads: the dense
    solve's BLAS threads (None: :func:`dense_threads`); the incremental fit uses one.
    The returned fit's ``method`` says which ran.
    """
    pts = np.asarray(points)
    b = np.asarray(rhs)
    sub_p, sub_b = (pts, b) if kept is None else (pts[kept], b[kept])
    m_all = int(np.unique(np.asarray(pts, dtype=np.float64), axis=0).shape[0]) \
        if pts.ndim == 2 and pts.shape[0] else 0
    n_threads = dense_threads(threads)
    choice = choose_method(m_all, int(sub_p.shape[0]), n_threads)
    if choice.method == "exact":
        return fit_exact(pts, b, normalization=normalization, threads=n_threads)
    history: list[tuple[int, float]] = []
    m_kept = int(sub_p.shape[0])

    over = [False]  # the heading passed the dense cost at the previous check

    def stop(n: int, err: float) -> bool:
        history.append((n, err))
        spent = incremental_seconds(m_kept, n)
        if spent >= choice.dense:
            return True
        heading = heading_for(history, float(tolerance)) if n >= HEADING_AFTER else None
        passed = heading is not None and \
            incremental_seconds(m_kept, min(heading, 1e9)) - spent > choice.dense
        give_up, over[0] = passed and over[0], passed  # twice in a row: not one plateau
        return give_up

    try:
        fit = fit_incremental(sub_p, sub_b, tolerance=tolerance, max_centers=max_centers,
                              normalization=normalization, selection=selection, stop=stop)
    except InputError:
        if kept is None or math.isinf(choice.dense):
            raise
        # the kept subset alone is degenerate (e.g. flat): the dense solve takes every point
        return fit_exact(pts, b, normalization=normalization, threads=n_threads)
    if math.isinf(choice.dense):
        return fit
    if fit.converged and (kept is None or all_errors(fit, pts, b) <= BOUNDARY_FACTOR
                          * float(tolerance)):
        return fit
    return fit_exact(pts, b, normalization=normalization, threads=n_threads)


def all_errors(fit: RbfFit, points: np.ndarray, rhs: np.ndarray, chunk: int = 4096) -> float:
    """Largest |rhs - b(points)| of ``fit`` over ``points`` (m, 3) model units, rhs (m, k)."""
    from scipy.spatial.distance import cdist

    x = fit.normalization.apply(points)
    worst = 0.0
    for a in range(0, x.shape[0], chunk):
        xa = x[a:a + chunk]
        val = fit.weights[0] + xa @ fit.weights[1:4]
        if fit.n_centers:
            val = val + (cdist(xa, fit.centers) ** 3) @ fit.weights[4:]
        worst = max(worst, float(np.abs(np.asarray(rhs[a:a + chunk], dtype=np.float64)
                                        - val).max()))
    return worst
