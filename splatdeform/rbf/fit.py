"""Incremental least-squares fit of a triharmonic RBF field (Botsch & Kobbelt 2005, section 4).

A = [Pi | Phi] with Pi = (1, x, y, z) at the m constraint points and one column
phi(|x_i - s_j|) = |x_i - s_j|^3 per center s_j; centers are constraint points taken in
farthest-point order (or residual-weighted farthest-point order). Householder QR adds one
column (one reflection) at a time; after column j the least-squares residual of every
right-hand-side column is Q [0; rows > j of Q^T rhs]. The tolerance bounds the largest constraint
error max_ic |r_ic| (docs/guides/edits.md, "Tolerance"): the tail 2-norm of Q^T rhs is a cheap
running bound, and r itself is recovered from the stored reflections once per block of columns.
Stop at the first block that meets the tolerance (at its first column that does), then solve
R W = Q1^T rhs once.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Literal

import numpy as np

from splatdeform.blas import blas_threads
from splatdeform.errors import InputError, ProcessingError
from splatdeform.rbf.defaults import DEFAULT_MAX_CENTERS, DEFAULT_TOLERANCE
from splatdeform.rbf.fps import squared_distances
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
    from scipy.linalg import lapack  # on first use: scipy.linalg costs ~0.1 s to import

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
    if np.all(tau != 0.0):  # T^-1 = diag(1 / tau) + strictly upper(V^T V): one solve
        inv = np.triu(gram, 1)
        inv[np.arange(nb), np.arange(nb)] = 1.0 / tau
        from scipy.linalg import solve_triangular

        return solve_triangular(inv, np.eye(nb), lower=False, check_finite=False)
    t = np.zeros((nb, nb))
    for i in range(nb):
        t[i, i] = tau[i]
        if i:
            t[:i, i] = -tau[i] * (t[:i, :i] @ gram[:i, i])
    return t


class _BlockedQR:
    """Householder QR built block by block; each block of reflections in compact-WY form
    H_i = I - V_i T_i V_i^T, Q = H_0 H_1 .. (applied block by block).

    v: (m, cap) explicit unit lower trapezoidal reflectors (block i in columns s_i .. s_i + b_i,
    rows >= s_i); blocks: (s_i, T_i (b_i, b_i) upper triangular); r: (cap, cap) the R factor.
    Only the leading ``cols`` columns are valid. One T per block, not one for all columns: a
    global T would cost another m p b flops per block to update (V_p^T V_b), a third of the fit.
    """

    def __init__(self, m: int, cap: int) -> None:
        self.m = m
        self.cols = 0
        self.v = np.zeros((m, cap), order="F")
        self.r = np.zeros((cap, cap), order="F")
        self.blocks: list[tuple[int, np.ndarray]] = []

    def _grow(self, need: int) -> None:
        cap = self.v.shape[1]
        if need <= cap:
            return
        new = max(need, 2 * cap)
        p = self.cols
        v = np.zeros((self.m, new), order="F")
        v[:, :p] = self.v[:, :p]
        r = np.zeros((new, new), order="F")
        r[:p, :p] = self.r[:p, :p]
        self.v, self.r = v, r

    def _reflector(self, s: int, t: np.ndarray) -> np.ndarray:
        return self.v[s:, s : s + t.shape[0]]

    def apply_qt(self, c: np.ndarray) -> None:
        """c (m, j) <- Q^T c in place (every stored block, in order)."""
        for s, t in self.blocks:
            vb, rows = self._reflector(s, t), c[s:]
            rows -= vb @ (t.T @ (vb.T @ rows))

    def apply_q(self, z: np.ndarray) -> None:
        """z (m, j) <- Q z in place (every stored block, in reverse order)."""
        for s, t in reversed(self.blocks):
            vb, rows = self._reflector(s, t), z[s:]
            rows -= vb @ (t @ (vb.T @ rows))

    def add_block(self, cblk: np.ndarray, qtb: np.ndarray) -> None:
        """Append the columns cblk (m, b) float64, Fortran-ordered (overwritten: Q^T cblk):
        apply Q^T (BLAS-3 products per stored block), QR the part below the current rows,
        store V_b, T_b, extend R, and apply the new reflections to qtb (m, k) in place."""
        p, nb, m = self.cols, cblk.shape[1], self.m
        if p + nb > m:
            raise ProcessingError(f"fit: cannot add {nb} columns to {p} with only {m} constraints")
        self._grow(p + nb)
        c = np.asarray(cblk, dtype=np.float64, order="F")  # the caller's fresh columns
        self.apply_qt(c)
        self.r[:p, p : p + nb] = c[:p]
        lower, tau = _geqrf(c[p:])
        self.r[p : p + nb, p : p + nb] = np.triu(lower[:nb])
        vb = self.v[p:, p : p + nb]
        vb[...] = lower[:, :nb]
        upper = np.triu_indices(nb)  # V: unit lower trapezoidal (np.tril of (m, b): 3x slower)
        vb[upper] = 0.0
        vb[np.arange(nb), np.arange(nb)] = 1.0
        tb = _larft(vb, tau)
        self.blocks.append((p, tb))
        self.cols = p + nb
        rows = qtb[p:]
        rows -= vb @ (tb.T @ (vb.T @ rows))

    def truncate(self, cols: int) -> None:
        """Keep the leading ``cols`` columns (an earlier state of the same incremental QR):
        T of the leading reflections of a block is the leading block of its T."""
        kept = []
        for s, t in self.blocks:
            if s >= cols:
                break
            kept.append((s, t[: cols - s, : cols - s] if s + t.shape[0] > cols else t))
        self.blocks = kept
        self.cols = cols

    def residual(self, qtb: np.ndarray, keep: int, m: int) -> np.ndarray:
        """The least-squares residual rhs - A W (m, k) using the leading ``keep`` columns.

        Q [0; rows >= keep of Q^T rhs] with all ``cols`` stored reflections: reflections after
        ``keep`` touch rows >= keep only, so this equals Q_keep [0; rows >= keep of Q_keep^T rhs]
        (the residual of the earlier state with ``keep`` columns). The m constraint rows are
        returned (the side rows below them are not constraints). Cost O(rows * cols * k).
        """
        z = np.zeros_like(qtb)
        z[keep:] = qtb[keep:]
        self.apply_q(z)
        return z[:m]


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


Selection = Literal["greedy", "fps"]



class _Centers:
    """Picks the next centers among the constraint points x (m, 3).

    "fps": farthest point order (deterministic start: the point farthest from the centroid).
    "greedy": residual-weighted farthest points: the first block is farthest-point order, then
    each pick maximises |r_i|_2 * d_i, the constraint's current residual (2-norm over the k
    columns: the size of its error in model units, sum_c r_ic delta_c, for a delta in no
    particular direction) times its distance to the nearest chosen center, so picks go where
    the field misses most while staying spread out. (The 2-norm, not the 1-norm: 340 centers
    instead of 433 on the paper scene, within +-4% on the others of
    ``benchmarks/fit_table.py``.)
    """

    def __init__(self, x: np.ndarray, selection: Selection) -> None:
        self.selection = selection
        self.coords = np.ascontiguousarray(x.T)  # (3, m): one contiguous row per coordinate
        diff = x - x.mean(axis=0)
        self._first = int(np.argmax(np.einsum("ij,ij->i", diff, diff)))
        self.dist2 = np.full(x.shape[0], np.inf)
        self.count = 0
        #: (m, b) squared distances of every point to the last block's picks (their kernel
        #: columns, without a second distance pass)
        self.block_d2 = np.zeros((x.shape[0], 0))
        self._tmp = np.empty(x.shape[0])

    def _take(self, i: int, d2: np.ndarray) -> None:
        """Pick i: d2 (m,) <- squared distances to it; fold them into the nearest distances."""
        np.minimum(self.dist2, squared_distances(self.coords, i, d2, self._tmp), out=self.dist2)
        self.count += 1

    def next_block(self, size: int, residual: np.ndarray | None) -> list[int]:
        """Up to ``size`` new center indices (fewer when only duplicates remain); their squared
        distance columns are left in :attr:`block_d2`."""
        out: list[int] = []
        d2 = np.empty((size, self.dist2.shape[0]))
        score2 = None
        if self.selection == "greedy" and residual is not None and self.count >= 16:
            score2 = np.einsum("ij,ij->i", residual, residual)  # argmax of |r|^2 d^2: no sqrt
        key = np.empty_like(self.dist2)
        for _ in range(size):
            if self.count == 0:
                i = self._first
            else:
                if score2 is None:
                    key = self.dist2
                else:
                    np.multiply(score2, self.dist2, out=key)
                i = int(np.argmax(key))
                if not self.dist2[i] > 0.0 or not key[i] > 0.0:
                    i = int(np.argmax(self.dist2))  # residual 0 there: fall back to farthest
                    if not self.dist2[i] > 0.0:
                        break  # only duplicates of chosen centers remain
            self._take(i, d2[len(out)])
            out.append(i)
        self.block_d2 = d2[: len(out)].T
        return out


def _block_sizes(block: int) -> Iterator[int]:
    size = min(block, 16)  # grow 16, 32, .. up to `block`: little overshoot for early stops
    while True:
        yield size
        size = min(block, 2 * size)


def fit_incremental(
    points: np.ndarray,
    rhs: np.ndarray,
    *,
    tolerance: float = DEFAULT_TOLERANCE,
    max_centers: int = DEFAULT_MAX_CENTERS,
    normalization: Normalization | None = None,
    block: int = 64,
    side_weight: float = 1.0,
    selection: Selection = "greedy",
    threads: int | None = 1,
    stop: Callable[[int, float], bool] | None = None,
) -> RbfFit:
    """Fit b(x) = [1, x, |x - s_j|^3] . W to ``rhs`` at ``points`` by incremental QR.

    points: (m, 3) constraint points in model units, m >= 4, spanning 3D.
    rhs: (m, k) float64 right-hand sides (affine coordinates M for a handle, spline coordinates
        for a curve, or displacements).
    tolerance: bound on the largest constraint error max_ic |r_ic|, r = rhs - A W, in the units
        of ``rhs`` (dimensionless for M). A constraint's error in model units for a later delta_c
        (k, 3) is then at most sum_c |r_ic| * max_c |delta_c[c]| <= k * tolerance * (largest
        control-point move). It is checked once per block of added columns on r recovered from
        the stored reflections; the fit stops at the first column of the first block that meets
        it.
    max_centers: most centers to add (also capped at m); when reached above the tolerance the
        fit is returned with ``converged=False``.
    normalization: model -> normalised coordinates; default ``Normalization.of(points)``.
    block: most center columns generated and factored per blocked step (blocks grow 16, 32, ..
        up to ``block``).
    side_weight: weight of the polyharmonic side conditions P^T w = 0 (sum_j w_j = 0,
        sum_j w_j s_j = 0), appended as 4 extra least-squares rows with right-hand side 0; 0
        disables them.
    selection: "greedy" (residual-weighted farthest points, the default: same deviation from the
        exact interpolant with fewer centers, see the fit table in docs/benchmarks.md) or "fps"
        (farthest point order, independent of the residual).
    threads: BLAS threads inside the fit (None leaves the pool alone); see :func:`blas_threads`.
    stop: called after each block with (centers so far, largest |r|); True abandons the fit
        (returned with ``converged=False``): ``fit.method: auto`` switches to the dense solve
        once the fit heads past its cost.

    Why side conditions: without them the least-squares weights are unconstrained in the
    polynomial directions, and as the center count nears the constraint count the system turns
    nearly square with huge, cancelling weights (1e7 seen) that make the field fly off far from
    the constraints. With them, n = m centers reproduce exactly the triharmonic interpolant
    (scipy's RBFInterpolator with kernel="cubic", degree=1), and fewer centers give its
    constrained least-squares approximation.

    Why blocked: the next ``block`` columns are generated ahead (from the residual at the start
    of the block for "greedy"). Each block applies all earlier reflections at once in compact-WY
    form (Q^T C = C - V T^T V^T C: three BLAS-3 products), factors its lower part with LAPACK
    ``dgeqrf`` and extends V and T, instead of a Python loop of one rank-1 reflection per column.
    It is numerically the same incremental Householder algorithm: stopping mid-block truncates R
    and Q^T rhs to the leading columns/rows, exactly the state the one-column loop reaches there.

    Returns an :class:`RbfFit` with centers (n, 3) and weights (4 + n, k) in normalised
    coordinates, the history of the tail 2-norms (1 + n, k), and the achieved max / RMS |r|.
    """
    pts, b = _check_inputs(points, rhs, tolerance, max_centers, block, normalization)
    if selection not in ("greedy", "fps"):
        raise InputError(f"selection: expected 'greedy' or 'fps', got {selection!r}")
    with blas_threads(threads):
        return _fit(pts, b, float(tolerance), int(max_centers), normalization, int(block),
                    float(side_weight), selection, stop)


def _fit(pts: np.ndarray, b: np.ndarray, tol: float, max_centers: int,
         normalization: Normalization | None, block: int, lam: float,
         selection: Selection, stop: Callable[[int, float], bool] | None = None) -> RbfFit:
    norm = normalization if normalization is not None else Normalization.of(pts)
    x = norm.apply(pts)
    m, k = b.shape
    side = 4 if lam > 0 else 0
    n_max = min(max_centers, m - 4 + side)

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
        d2 = picker.block_d2  # (m, len(idx)) squared distances, from the picks
        np.sqrt(d2, out=cols_[:m])
        cols_[:m] *= d2  # |x - s|^3
        if side:
            cols_[m] = lam
            cols_[m + 1:] = lam * x[idx].T
        return cols_

    def max_error(cols: int) -> tuple[float, np.ndarray]:
        r = state.residual(qtb, cols, m)
        return float(np.abs(r).max()), r

    history = [np.linalg.norm(qtb[4:], axis=0)]
    order: list[int] = []
    err, resid = max_error(state.cols)
    converged = err <= tol
    picker = _Centers(x, selection)
    sizes = _block_sizes(block)
    while not converged and len(order) < n_max:
        new = picker.next_block(min(next(sizes), n_max - len(order)), resid)
        if not new:
            break  # only duplicates of picked centers remain
        start = state.cols
        state.add_block(center_columns(new), qtb)
        tails = _tail_residuals(qtb[start:])[: len(new)]
        err, resid = max_error(state.cols)
        used = len(new)
        if err <= tol:
            used, err, resid = _first_meeting(max_error, start, len(new), tol, tails,
                                              (err, resid))
            converged = True
        history.extend(tails[:used])
        order.extend(new[:used])
        state.truncate(start + used)
        if not converged and stop is not None and stop(len(order), err):
            break

    cols = state.cols
    hist = np.minimum.accumulate(np.vstack(history), axis=0)  # rounding-level monotonicity
    r_tri = np.triu(state.r[:cols, :cols])
    from scipy.linalg import solve_triangular

    weights = solve_triangular(r_tri, qtb[:cols], lower=False, check_finite=False)
    if not np.all(np.isfinite(weights)):
        raise ProcessingError("fit: the triangular solve produced non-finite weights")
    idx = np.asarray(order, dtype=np.int64)
    return RbfFit(
        centers=x[idx].copy() if idx.size else np.zeros((0, 3)),
        weights=np.ascontiguousarray(weights),
        normalization=norm,
        residuals=hist,
        converged=bool(err <= tol),
        tolerance=tol,
        max_error=err,
        rms_error=float(np.sqrt(np.mean(resid * resid))),
    )


def _first_meeting(max_error, start: int, count: int, tol: float, tails: np.ndarray,
                   at_end: tuple[float, np.ndarray]) -> tuple[int, float, np.ndarray]:
    """Fewest leading columns of the last block (1..count) whose max |r| meets ``tol``.

    The max-norm is at most the tail 2-norm, so columns whose tail norm already meets the
    tolerance are an upper bound; below it, bisection on recovered residuals (the max error is
    non-increasing in practice; whatever is returned was checked). Returns (used, err, r).
    """
    lo, hi = 0, count  # hi meets the tolerance, lo is not known to
    best = (count, *at_end)
    ok_tail = np.flatnonzero(np.all(tails <= tol, axis=1))
    if ok_tail.size and ok_tail[0] + 1 < hi:
        hi = int(ok_tail[0]) + 1
        best = (hi, *max_error(start + hi))
    while hi - lo > 1:
        mid = (lo + hi) // 2
        e, r = max_error(start + mid)
        if e <= tol:
            hi, best = mid, (mid, e, r)
        else:
            lo = mid
    return best
