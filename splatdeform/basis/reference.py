"""The numpy float64 reference basis (the oracle the OpenCL backend is checked against).

For a normalised point p (see :class:`~splatdeform.rbf.result.Normalization`):

    b(p)      = [1, p, |p - s_j|^3] . W                      (k,)
    grad b(p) = [0, I3, 3 |p - s_j| (p - s_j)] . W / scale   (k, 3) model units

Vectorised over chunks of points so the (N_chunk, n) temporaries stay under a byte budget; per
chunk one ``cdist`` for r and two BLAS matmuls (values, and all 3 gradient components stacked as
one (n, 4k) product: grad_d = p_d (G Wc) - G (s_d Wc) with G = 3 r).
"""

from __future__ import annotations

import numpy as np

from splatdeform.basis.checks import check_fit, check_points
from splatdeform.basis.result import Basis
from splatdeform.errors import InputError
from splatdeform.rbf.result import RbfFit

# (N_chunk, n) float64 arrays alive at once per chunk: r, phi / G, and the matmul outputs.
_TEMPS_PER_ENTRY = 3


def _chunk_rows(n_centers: int, k: int, gradients: bool, max_chunk_bytes: int) -> int:
    per_row = 8 * (_TEMPS_PER_ENTRY * max(n_centers, 1) + (13 if gradients else 2) * k + 6)
    return max(1, int(max_chunk_bytes) // per_row)


def compute_basis(
    points: np.ndarray,
    fit: RbfFit,
    *,
    gradients: bool = True,
    max_chunk_bytes: int = 256 * 2**20,
) -> Basis:
    """Evaluate the fitted basis (and its gradients) at ``points``.

    points: (N, 3) model units (any float dtype; computed in float64).
    fit: the :class:`RbfFit` (centers and weights in normalised coordinates).
    gradients: also return grad b in model units (divided by the normalisation scale).
    max_chunk_bytes: budget for the per-chunk temporaries (about 3 (N_chunk, n) float64 arrays).

    Returns a :class:`Basis` with values (N, k) float64 and gradients (N, k, 3) float64 or None.
    """
    pts = check_points(points)
    check_fit(fit)
    if int(max_chunk_bytes) < 1:
        raise InputError(
            f"max_chunk_bytes: expected a positive byte count, got {max_chunk_bytes!r}"
        )
    w = np.asarray(fit.weights, dtype=np.float64)
    s = np.asarray(fit.centers, dtype=np.float64)
    n, k = s.shape[0], w.shape[1]
    total = pts.shape[0]
    values = np.empty((total, k), dtype=np.float64)
    grads = np.empty((total, k, 3), dtype=np.float64) if gradients else None
    if total == 0:
        return Basis(values=values, gradients=grads)
    from scipy.spatial.distance import cdist  # on first use (scipy.spatial: ~0.2 s import)

    w_lin = w[1:4]  # (3, k)
    w_c = w[4:]  # (n, k)
    # [Wc, s_x Wc, s_y Wc, s_z Wc]: (n, 4k) so that G @ stacked gives G Wc and G (s_d Wc).
    stacked = np.concatenate([w_c] + [s[:, d : d + 1] * w_c for d in range(3)], axis=1)
    inv_scale = 1.0 / fit.normalization.scale
    rows = _chunk_rows(n, k, gradients, max_chunk_bytes)
    for lo in range(0, total, rows):
        hi = min(total, lo + rows)
        p = fit.normalization.apply(pts[lo:hi])
        out = p @ w_lin
        out += w[0]
        if n == 0:
            values[lo:hi] = out
            if grads is not None:
                grads[lo:hi] = (w_lin.T * inv_scale)[None]
            continue
        r = cdist(p, s)
        if grads is not None:
            g = np.multiply(r, 3.0)
            gw = g @ stacked  # (c, 4k)
            del g
        np.power(r, 3, out=r)
        out += r @ w_c
        del r
        values[lo:hi] = out
        if grads is not None:
            gwc = gw[:, :k]
            for d in range(3):
                comp = p[:, d : d + 1] * gwc
                comp -= gw[:, (d + 1) * k : (d + 2) * k]
                comp += w_lin[d]
                comp *= inv_scale
                grads[lo:hi, :, d] = comp
    return Basis(values=values, gradients=grads)


def evaluate_field(
    points: np.ndarray, fit: RbfFit, *, max_chunk_bytes: int = 256 * 2**20
) -> np.ndarray:
    """The fitted field b(p) at ``points`` (N, 3) model units: (N, k) float64 (no gradients)."""
    return compute_basis(points, fit, gradients=False, max_chunk_bytes=max_chunk_bytes).values
