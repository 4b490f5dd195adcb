"""The exact triharmonic interpolant: every constraint a center, one dense solve.

    [ Phi  P ] [w]   [rhs]
    [ P^T  0 ] [a] = [ 0 ]      Phi_ij = |x_i - x_j|^3,  P = [1, x]   (normalised coordinates)

This is the minimiser of the third-order energy through all constraints (``fit.method: exact``),
the same interpolant as scipy's ``RBFInterpolator(kernel="cubic", degree=1)``, and the in-house
oracle of the incremental fitter. The matrix is symmetric indefinite; projected onto the side
conditions it is positive definite and is factored by one Cholesky (m^3 / 3 flops, half an LU;
:func:`_solve`) on :func:`dense_threads` threads (the kernel matrix and a blocked Cholesky on
Python threads over one-threaded BLAS, so that a busy machine does not stall it:
:mod:`splatdeform.rbf.cholesky`). It costs O(m^3) time and 8 m^2 bytes, so it is refused above
:data:`EXACT_MAX_CONSTRAINTS`.
"""

from __future__ import annotations

import os
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from splatdeform.blas import blas_threads
from splatdeform.errors import InputError, ProcessingError
from splatdeform.rbf.kernel import cubed_distance_rows, cubed_distances
from splatdeform.rbf.result import Normalization, RbfFit

#: Measured on the 2-core development machine: 8,000 constraints take ~7 s and 0.5 GB; the
#: cost grows with m^3, so 12,000 is ~25 s and 1.2 GB. Beyond that use the incremental fit.
EXACT_MAX_CONSTRAINTS = 12_000

#: Environment variables that set the dense solve's threads, first found wins (after an
#: explicit ``threads``): our own, then the usual BLAS / OpenMP ones.
THREAD_VARIABLES = ("SPLATDEFORM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                    "OMP_NUM_THREADS")


def dense_threads(threads: int | None = None) -> int:
    """Threads of the dense solve: ``threads`` when given (``fit.threads``), else the
    first of :data:`THREAD_VARIABLES` set to a positive integer, else the CPUs this process may
    run on (``len(os.sched_getaffinity(0))``)."""
    if threads is not None:
        if int(threads) != threads or threads < 1:
            raise InputError(f"threads: expected an integer >= 1, got {threads!r}")
        return int(threads)
    for name in THREAD_VARIABLES:
        value = os.environ.get(name, "").strip()
        if value.isdigit() and int(value) > 0:
            return int(value)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def distinct_rows(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, inverse) of the rows of ``pts`` (m, 3): first (u,) int64 ascending, the index
    of each distinct row's first occurrence; inverse (m,) the position in ``first`` of each
    row's copy. One lexsort and a comparison of neighbours (``np.unique(axis=0)`` sorts
    structured rows, several times slower: as much as a small dense solve)."""
    m = pts.shape[0]
    if m == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order = np.lexsort(pts.T[::-1])                 # stable: copies by ascending index
    srt = pts[order]
    new = np.ones(m, dtype=bool)
    new[1:] = np.any(srt[1:] != srt[:-1], axis=1)
    if new.all():
        return np.arange(m, dtype=np.int64), np.arange(m, dtype=np.int64)
    group = np.cumsum(new) - 1                      # sorted position -> group
    firsts = order[new]                             # group -> first occurrence
    rank = np.empty(firsts.size, dtype=np.int64)
    by_first = np.argsort(firsts, kind="stable")
    rank[by_first] = np.arange(firsts.size)
    inverse = np.empty(m, dtype=np.int64)
    inverse[order] = rank[group]
    return firsts[by_first].astype(np.int64), inverse


def unique_constraints(pts: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct constraint points (u, 3) in first-seen order and their values (u, k).

    Raises InputError when duplicates carry different values."""
    first, inverse = distinct_rows(pts)
    if first.size == pts.shape[0]:
        return pts, b
    pts_u = pts[first]
    b_u = b[first]
    if not np.allclose(b_u[inverse], b, rtol=0, atol=1e-12 * max(1.0, np.abs(b).max())):
        raise InputError("points: duplicate constraint points with different prescribed values")
    return pts_u, b_u


def fit_exact(
    points: np.ndarray,
    rhs: np.ndarray,
    *,
    normalization: Normalization | None = None,
    threads: int | None = None,
) -> RbfFit:
    """Interpolate ``rhs`` (m, k) at ``points`` (m, 3) exactly with r^3 + a linear polynomial.

    Duplicate points must carry equal right-hand sides (they are merged; conflicting values
    raise InputError). Returns an :class:`RbfFit` whose centers are all distinct constraint
    points (normalised) and whose weights are (4 + n, k), rows [1, x, y, z, phi_1 .. phi_n].
    threads: threads of the solve (None: :func:`dense_threads`).
    """
    from splatdeform.rbf.fit import _check_inputs

    pts, b = _check_inputs(points, rhs, 0.0, 0, 1, normalization)
    pts_u, b_u = unique_constraints(pts, b)
    m = pts_u.shape[0]
    if m > EXACT_MAX_CONSTRAINTS:
        raise InputError(
            f"fit.method: exact: {m:,} constraints exceed the limit of {EXACT_MAX_CONSTRAINTS:,} "
            "(O(m^3) time, 8 m^2 bytes); use fit.method: incremental")
    norm = normalization if normalization is not None else Normalization.of(pts_u)
    x = norm.apply(pts_u)
    with blas_threads(1):  # the factorisation alone uses more (:mod:`splatdeform.rbf.cholesky`)
        poly, w = _solve(x, b_u, dense_threads(threads))
    weights = np.vstack([poly, w])  # rows [1, x, y, z, phi_j]
    k = b.shape[1]
    return RbfFit(centers=x, weights=np.ascontiguousarray(weights), normalization=norm,
                  residuals=np.zeros((1, k)), converged=True, tolerance=0.0, max_error=0.0,
                  rms_error=0.0, method="exact")


def _kernel_times(x: np.ndarray, v: np.ndarray, y: np.ndarray, threads: int = 1) -> np.ndarray:
    """The kernel matrix Phi = |x_i - x_j|^3 (m, m) of x (m, 3), Fortran-ordered for LAPACK
    with only its lower triangle filled (symmetric: the upper triangle of the C-ordered array
    built block by block, :func:`cubed_distance_rows`), and y (m, 4) += Phi v for v (m, 4),
    accumulated from each block while it is in cache (no pass over the whole matrix).

    threads: row ranges of equal area of the triangle built on that many Python threads (numpy
    releases the interpreter lock in its loops and products), each with its own sum of Phi v;
    one below :data:`splatdeform.rbf.cholesky.MIN_THREADED` points, as the factorisation.
    """
    from splatdeform.rbf import cholesky

    n = x.shape[0]
    phi = np.empty((n, n))

    def rows(first: int, end: int) -> np.ndarray:
        acc = np.zeros_like(y)
        for a, e, blk in cubed_distance_rows(x, x, phi, upper=True, rows=(first, end)):
            acc[a:e] += blk @ v[a:]                 # blk: columns a..
            acc[e:] += blk[:, e - a:].T @ v[a:e]
        return acc

    parts = max(1, int(threads)) if n >= cholesky.MIN_THREADED else 1
    if parts == 1:
        y += rows(0, n)
        return phi.T
    cuts = [int(round(n * (1.0 - np.sqrt(1.0 - k / parts)))) for k in range(parts + 1)]
    with ThreadPoolExecutor(parts) as pool:
        for acc in pool.map(lambda k: rows(cuts[k], cuts[k + 1]), range(parts)):
            y += acc
    return phi.T


def _solve(x: np.ndarray, b: np.ndarray, threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(polynomial part (4, k), center weights (m, k)) of the interpolation system; the kernel
    matrix and its Cholesky factorisation on ``threads`` threads, the rest on the caller's BLAS
    threads.

    r^3 is conditionally positive definite of order 2: on the vectors w with P^T w = 0 the
    quadratic form w^T Phi w is positive. With P = Q [R; 0] (Householder, Q = I - V T V^T),
    w = Q [0; z] satisfies the side conditions, and the system splits into
    A22 z = (Q^T rhs)_2 with A22 = (Q^T Phi Q)_22 symmetric positive definite (one Cholesky,
    m^3 / 3 flops, :func:`splatdeform.rbf.cholesky.factor_lower`) and
    R a = (Q^T rhs)_1 - A12 z.
    Q^T Phi Q = Phi - Z V^T - V Z^T, so A22 is the kernel matrix of the points 5.. (its
    lower triangle built by blocks, Phi V summed from them, factored in place) plus one
    rank-8 symmetric update (BLAS syr2k); only the first 4 rows of Phi are needed besides.
    Should rounding make A22 not positive definite (near-duplicate points), the full saddle
    system is solved by the symmetric-indefinite factorisation instead.
    """
    from scipy.linalg import LinAlgError, blas, lapack, solve_triangular

    from splatdeform.rbf.cholesky import factor_lower, solve_lower
    from splatdeform.rbf.fit import _larft

    m = x.shape[0]
    poly = np.empty((m, 4))
    poly[:, 0] = 1.0
    poly[:, 1:] = x
    qr, tau, _, info = lapack.dgeqrf(poly)
    if info != 0:
        raise ProcessingError(f"fit: LAPACK dgeqrf failed (info={info})")
    v = np.tril(qr[:, :4], -1)
    v[np.arange(4), np.arange(4)] = 1.0
    r = np.triu(qr[:4, :4])
    t = _larft(v, tau)
    top = cubed_distances(x[:4], x)                     # Phi[:4, :] (4, m)
    y = np.empty((m, 4))                                # Phi V
    y[:4] = top @ v
    y[4:] = top[:, 4:].T @ v[:4]
    a22 = _kernel_times(x[4:], v[4:], y[4:], threads)   # Phi[4:, 4:], lower triangle
    z = y @ t - 0.5 * v @ (t.T @ (v.T @ y) @ t)         # Q^T Phi Q = Phi - Z V^T - V Z^T
    c = b - v @ (t.T @ (v.T @ b))                       # Q^T rhs
    try:
        a22 = blas.dsyr2k(-1.0, z[4:], v[4:], beta=1.0, c=a22, lower=1, overwrite_c=1)
        zz = solve_lower(factor_lower(a22, threads), c[4:])
        a12 = top[:, 4:] - z[:4] @ v[4:].T - v[:4] @ z[4:].T
        a = solve_triangular(r, c[:4] - a12 @ zz, lower=False, check_finite=False)
        full = np.zeros_like(c)
        full[4:] = zz
        w = full - v @ (t @ (v.T @ full))               # Q [0; z]
    except LinAlgError:
        with blas_threads(threads):
            a, w = _solve_indefinite(x, b)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(w))):
        raise ProcessingError("fit: the exact interpolation system is singular")
    return a, w


def _solve_indefinite(x: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The saddle system [[Phi, P], [P^T, 0]] by the symmetric-indefinite solver (?sysv)."""
    from scipy.linalg import LinAlgError, LinAlgWarning, solve

    m, k = b.shape
    lhs = np.zeros((m + 4, m + 4))
    cubed_distances(x, x, out=lhs[:m, :m])
    lhs[:m, m] = lhs[m, :m] = 1.0
    lhs[:m, m + 1:] = x
    lhs[m + 1:, :m] = x.T
    full = np.zeros((m + 4, k))
    full[:m] = b
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LinAlgWarning)  # judged by the finite check
        try:
            sol = solve(lhs, full, assume_a="sym", overwrite_a=True, overwrite_b=True,
                        check_finite=False)
        except (LinAlgError, ValueError) as exc:
            raise ProcessingError(f"fit: the exact interpolation system is singular ({exc})"
                                  ) from exc
    return sol[m:], sol[:m]
