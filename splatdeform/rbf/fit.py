"""Incremental least-squares fit of a triharmonic RBF field (Botsch & Kobbelt 2005, section 4).

A = [Pi | Phi] with Pi = (1, x, y, z) at the m constraint points and one column
phi(|x_i - s_j|) = |x_i - s_j|^3 per center s_j; centers are constraint points taken in
farthest-point order. Householder QR adds one column (one reflection) at a time; after column j
the least-squares residual of every right-hand-side column is the norm of the rows > j of
Q^T rhs. Stop at the first column where every residual meets the tolerance, then solve
R W = Q1^T rhs once.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.linalg import lapack, solve_triangular
from scipy.spatial.distance import cdist

from splatdeform.errors import InputError, ProcessingError
from splatdeform.rbf.fps import iter_farthest_points
from splatdeform.rbf.kernel import triharmonic
from splatdeform.rbf.result import Normalization, RbfFit

_NB = 64  # LAPACK workspace block size hint


def _check_inputs(
    points: np.ndarray,
    rhs: np.ndarray,
    tolerance: float,
    max_centers: int,
    block: int,
    normalization: Normalization | None,
) -> tuple[np.ndarray, np.ndarray]:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points: expected an (m, 3) array of constraint points, got {pts.shape}")
    if not np.issubdtype(pts.dtype, np.number):
        raise InputError(f"points: expected a numeric array, got dtype {pts.dtype}")
    pts = pts.astype(np.float64)
    m = pts.shape[0]
    if m < 4:
        raise InputError(
            f"points: expected at least 4 constraint points for the linear part, got {m}"
        )
    if not np.all(np.isfinite(pts)):
        raise InputError("points: expected finite coordinates, found NaN or inf")
    b = np.asarray(rhs)
    if b.ndim != 2 or b.shape[0] != m or b.shape[1] < 1:
        raise InputError(
            f"rhs: expected an (m, k) array with m = {m} rows and k >= 1, got {b.shape}"
        )
    if not np.issubdtype(b.dtype, np.number):
        raise InputError(f"rhs: expected a numeric array, got dtype {b.dtype}")
    b = b.astype(np.float64)
    if not np.all(np.isfinite(b)):
        raise InputError("rhs: expected finite values, found NaN or inf")
    tol = float(tolerance)
    if not np.isfinite(tol) or tol < 0:
        raise InputError(f"tolerance: expected a finite absolute residual >= 0, got {tolerance!r}")
    if int(max_centers) != max_centers or max_centers < 0:
        raise InputError(f"max_centers: expected an integer >= 0, got {max_centers!r}")
    if int(block) != block or block < 1:
        raise InputError(f"block: expected an integer >= 1, got {block!r}")
    if normalization is not None:
        if not isinstance(normalization, Normalization):
            raise InputError(
                "normalization: expected a Normalization or None, got "
                f"{type(normalization).__name__}"
            )
        if not (np.isfinite(normalization.scale) and normalization.scale > 0):
            raise InputError(f"normalization: expected scale > 0, got {normalization.scale!r}")
    # Affine independence: the centred points must span 3 dimensions (Pi full column rank).
    centred = pts - pts.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[0] == 0 or sv[2] <= 1e-10 * sv[0]:
        raise InputError(
            "points: expected constraint points spanning 3D (not all on one plane, line or point) "
            "for the linear part"
        )
    return pts, b


def _geqrf(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    qr, tau, _, info = lapack.dgeqrf(a, lwork=max(1, a.shape[1]) * _NB, overwrite_a=1)
    if info != 0:
        raise ProcessingError(f"fit: LAPACK dgeqrf failed (info={info})")
    return qr, tau


def _larft(v: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Upper triangular T with H_1 .. H_b = I - V T V^T (LAPACK dlarft, forward, columnwise).

    v: (r, b) unit lower trapezoidal reflectors; tau: (b,). Robust to tau = 0 (H = I).
    """
    nb = tau.shape[0]
    gram = v.T @ v
    t = np.zeros((nb, nb))
    for i in range(nb):
        t[i, i] = tau[i]
        if i:
            t[:i, i] = -tau[i] * (t[:i, :i] @ gram[:i, i])
    return t


class _BlockedQR:
    """Householder QR built block by block in compact-WY form Q = I - V T V^T.

    v: (m, cap) explicit unit lower trapezoidal reflectors; t: (cap, cap) upper triangular;
    r: (cap, cap) the R factor. Only the leading ``cols`` columns are valid.
    """

    def __init__(self, m: int, cap: int) -> None:
        self.m = m
        self.cols = 0
        self.v = np.zeros((m, cap), order="F")
        self.t = np.zeros((cap, cap), order="F")
        self.r = np.zeros((cap, cap), order="F")

    def _grow(self, need: int) -> None:
        cap = self.v.shape[1]
        if need <= cap:
            return
        new = max(need, 2 * cap)
        p = self.cols
        v = np.zeros((self.m, new), order="F")
        v[:, :p] = self.v[:, :p]
        t = np.zeros((new, new), order="F")
        t[:p, :p] = self.t[:p, :p]
        r = np.zeros((new, new), order="F")
        r[:p, :p] = self.r[:p, :p]
        self.v, self.t, self.r = v, t, r

    def add_block(self, cblk: np.ndarray, qtb: np.ndarray) -> None:
        """Append the columns cblk (m, b): apply Q^T (3 BLAS-3 products), QR the part below the
        current rows, extend V, T, R, and apply the new reflections to qtb (m, k) in place."""
        p, nb, m = self.cols, cblk.shape[1], self.m
        if p + nb > m:
            raise ProcessingError(f"fit: cannot add {nb} columns to {p} with only {m} constraints")
        self._grow(p + nb)
        c = np.array(cblk, dtype=np.float64, order="F")
        if p:
            vp, tp = self.v[:, :p], self.t[:p, :p]
            c -= vp @ (tp.T @ (vp.T @ c))  # Q^T c = c - V T^T V^T c
        self.r[:p, p : p + nb] = c[:p]
        lower, tau = _geqrf(c[p:])
        vb = np.tril(lower[:, :nb], -1)
        vb[np.arange(nb), np.arange(nb)] = 1.0
        self.r[p : p + nb, p : p + nb] = np.triu(lower[:nb])
        self.v[p:, p : p + nb] = vb
        tb = _larft(vb, tau)
        if p:
            # T = [[T_p, -T_p (V_p^T V_b) T_b], [0, T_b]]
            self.t[:p, p : p + nb] = -(tp @ ((self.v[p:, :p].T @ vb) @ tb))
        self.t[p : p + nb, p : p + nb] = tb
        self.cols = p + nb
        rows = qtb[p:]
        rows -= vb @ (tb.T @ (vb.T @ rows))
        qtb[p:] = rows

    def truncate(self, cols: int) -> None:
        """Keep the leading ``cols`` columns (an earlier state of the same incremental QR)."""
        self.cols = cols


def _tail_residuals(rows: np.ndarray) -> np.ndarray:
    """Norms of rows[i + 1:] per column for i = 0 .. len(rows) - 1: (len(rows), k).

    ``rows`` are the rows p.. of Q^T rhs after the block's reflections. Reflection p + i touches
    rows >= p + i only, so the norm of rows > p + i is final once reflection p + i is applied:
    the residual after column p + i is sqrt of a reverse cumulative sum of squares.
    """
    sq = rows * rows
    tail = np.cumsum(sq[::-1], axis=0)[::-1]  # tail[i] = sum_{r >= i} sq[r]
    after = np.zeros_like(tail)
    after[:-1] = tail[1:]
    return np.sqrt(after)


def fit_incremental(
    points: np.ndarray,
    rhs: np.ndarray,
    *,
    tolerance: float,
    max_centers: int = 2000,
    normalization: Normalization | None = None,
    block: int = 64,
    side_weight: float = 1.0,
) -> RbfFit:
    """Fit b(x) = [1, x, |x - s_j|^3] . W to ``rhs`` at ``points`` by incremental QR.

    points: (m, 3) constraint points in model units, m >= 4, spanning 3D.
    rhs: (m, k) float64 right-hand sides (affine coordinates M for a handle, or displacements).
    tolerance: ABSOLUTE bound on the least-squares residual ||Q2^T rhs[:, c]||_2 of every column c;
        it bounds the largest constraint error of that column.
    max_centers: most centers to add (also capped at m - 4); when reached unconverged the fit is
        returned with ``converged=False``.
    normalization: model -> normalised coordinates; default ``Normalization.of(points)``.
    block: most center columns generated and factored per blocked step (blocks grow 16, 32, ..
        up to ``block`` so an early stop wastes few columns).
    side_weight: weight of the polyharmonic side conditions P^T w = 0 (sum_j w_j = 0,
        sum_j w_j s_j = 0), appended as 4 extra least-squares rows with right-hand side 0; 0
        disables them.

    Why side conditions: without them the least-squares weights are unconstrained in the
    polynomial directions, and as the center count nears the constraint count the system turns
    nearly square with huge, cancelling weights (1e7 seen) that make the field fly off far from
    the constraints (a curve bend moved free points 100x more than any control point). With them,
    n = m centers reproduce exactly the triharmonic interpolant (scipy's RBFInterpolator with
    kernel="cubic", degree=1), and fewer centers give its constrained least-squares
    approximation. The residual read from Q^T rhs then includes the side rows, so it still bounds
    every constraint error.

    Returns an :class:`RbfFit` with centers (n, 3) and weights (4 + n, k) in normalised
    coordinates and the residual history (1 + n, k): one row after the polynomial block (0
    centers is a valid result, e.g. for an affine rhs), one per added center, non-increasing.

    Why blocked: the center order (farthest point sampling among the constraint points) does not
    depend on the QR, so the next ``block`` columns can be generated ahead. Each block applies all
    earlier reflections at once in compact-WY form (Q^T C = C - V T^T V^T C: three BLAS-3
    products), factors its lower part with LAPACK ``dgeqrf`` and extends V and T (dlarft
    recurrence), instead of a Python loop of one rank-1 reflection per column. It is numerically
    the same incremental Householder algorithm: column j of R and rows < j of Q^T rhs are final
    once reflection j is applied (later reflections touch rows >= their own index only), and the
    residual after each column of the block is read from reverse cumulative sums of squares of
    the rows of Q^T rhs. Stopping mid-block truncates R and Q^T rhs to the leading columns/rows,
    which is exactly the state the one-column-at-a-time loop would have reached there.
    """
    pts, b = _check_inputs(points, rhs, tolerance, max_centers, block, normalization)
    tol = float(tolerance)
    norm = normalization if normalization is not None else Normalization.of(pts)
    x = norm.apply(pts)
    m, k = b.shape
    lam = float(side_weight)
    side = 4 if lam > 0 else 0
    n_max = min(int(max_centers), m - 4 + side)
    block = int(block)

    rows = m + side
    state = _BlockedQR(rows, 4 + min(n_max, max(block, 256)))
    poly = np.zeros((rows, 4), dtype=np.float64, order="F")
    poly[:m, 0] = 1.0
    poly[:m, 1:4] = x
    qtb = np.zeros((rows, k), dtype=np.float64, order="F")
    qtb[:m] = b
    state.add_block(poly, qtb)

    def center_columns(idx: list[int]) -> np.ndarray:
        cols_ = np.empty((rows, len(idx)), dtype=np.float64, order="F")
        cols_[:m] = triharmonic(cdist(x, x[idx]))
        if side:
            cols_[m] = lam
            cols_[m + 1:] = lam * x[idx].T
        return cols_

    history = [np.linalg.norm(qtb[4:], axis=0)]
    order: list[int] = []
    converged = bool(np.all(history[0] <= tol))
    picks = iter_farthest_points(x)
    size = min(block, 16)  # grow 16, 32, .. up to `block`: little overshoot for early stops
    while not converged and len(order) < n_max:
        new = list(itertools.islice(picks, min(size, n_max - len(order))))
        size = min(block, 2 * size)
        if not new:
            break  # only duplicates of picked centers remain
        nb = len(new)
        cols = state.cols
        state.add_block(center_columns(new), qtb)
        res = _tail_residuals(qtb[cols:])[:nb]
        ok = np.all(res <= tol, axis=1)
        used = int(np.argmax(ok)) + 1 if ok.any() else nb
        history.extend(res[:used])
        order.extend(new[:used])
        state.truncate(cols + used)
        converged = bool(ok.any())

    cols = state.cols
    hist = np.minimum.accumulate(np.vstack(history), axis=0)  # rounding-level monotonicity
    r = np.triu(state.r[:cols, :cols])
    weights = solve_triangular(r, qtb[:cols], lower=False, check_finite=False)
    if not np.all(np.isfinite(weights)):
        raise ProcessingError("fit: the triangular solve produced non-finite weights")
    idx = np.asarray(order, dtype=np.int64)
    return RbfFit(
        centers=x[idx].copy() if idx.size else np.zeros((0, 3)),
        weights=np.ascontiguousarray(weights),
        normalization=norm,
        residuals=hist,
        converged=bool(np.all(hist[-1] <= tol)),
        tolerance=tol,
    )
