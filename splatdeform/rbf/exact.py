"""The exact triharmonic interpolant: every constraint a center, one dense solve.

    [ Phi  P ] [w]   [rhs]
    [ P^T  0 ] [a] = [ 0 ]      Phi_ij = |x_i - x_j|^3,  P = [1, x]   (normalised coordinates)

This is the minimiser of the third-order energy through all constraints (``fit.method: exact``),
the same interpolant as scipy's ``RBFInterpolator(kernel="cubic", degree=1)``, and the in-house
oracle of the incremental fitter. It costs O(m^3) time and 8 (m + 4)^2 bytes, so it is refused
above :data:`EXACT_MAX_CONSTRAINTS`.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import LinAlgError, lu_factor, lu_solve

from splatdeform.errors import InputError, ProcessingError
from splatdeform.rbf.kernel import kernel_matrix
from splatdeform.rbf.result import Normalization, RbfFit

#: Measured on the 2-core development machine: 8,000 constraints take ~7 s and 0.5 GB; the
#: cost grows with m^3, so 12,000 is ~25 s and 1.2 GB. Beyond that use the incremental fit.
EXACT_MAX_CONSTRAINTS = 12_000


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
    threads: BLAS threads for the solve (None: the pool's default, one dense LU uses them well).
    """
    from splatdeform.rbf.fit import _check_inputs, blas_threads

    pts, b = _check_inputs(points, rhs, 0.0, 0, 1, normalization)
    uniq, first, inverse = np.unique(pts, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(first)  # keep the constraints' order
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    pts_u = uniq[order]
    b_u = b[first[order]]
    if not np.allclose(b_u[rank[inverse]], b, rtol=0, atol=1e-12 * max(1.0, np.abs(b).max())):
        raise InputError("points: duplicate constraint points with different prescribed values")
    m = pts_u.shape[0]
    if m > EXACT_MAX_CONSTRAINTS:
        raise InputError(
            f"fit.method: exact: {m:,} constraints exceed the limit of {EXACT_MAX_CONSTRAINTS:,} "
            "(O(m^3) time, 8 m^2 bytes); use fit.method: incremental")
    norm = normalization if normalization is not None else Normalization.of(pts_u)
    x = norm.apply(pts_u)
    k = b.shape[1]
    lhs = np.zeros((m + 4, m + 4))
    lhs[:m, :m] = kernel_matrix(x, x)
    lhs[:m, m] = lhs[m, :m] = 1.0
    lhs[:m, m + 1:] = x
    lhs[m + 1:, :m] = x.T
    full = np.zeros((m + 4, k))
    full[:m] = b_u
    with blas_threads(threads):
        try:
            sol = lu_solve(lu_factor(lhs, overwrite_a=True, check_finite=False), full,
                           check_finite=False)
        except (LinAlgError, ValueError) as exc:
            raise ProcessingError(f"fit: the exact interpolation system is singular ({exc})"
                                  ) from exc
    if not np.all(np.isfinite(sol)):
        raise ProcessingError("fit: the exact interpolation system is singular")
    weights = np.vstack([sol[m:], sol[:m]])  # rows [1, x, y, z, phi_j]
    return RbfFit(centers=x, weights=np.ascontiguousarray(weights), normalization=norm,
                  residuals=np.zeros((1, k)), converged=True, tolerance=0.0, max_error=0.0,
                  rms_error=0.0, method="exact")
