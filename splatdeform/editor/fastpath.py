"""Per-frame Gaussian covariances for the editor, cache-blocked like
:func:`splatdeform.deform.arrays.deform_frame`: Sigma' = J Sigma J^T on the 6 upper-triangle entries
(xx, xy, xz, yy, yz, zz), one chunk of points at a time, never a (N, 3, 3) temporary."""

from __future__ import annotations

import numpy as np

_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def covariance_frame(gradients: np.ndarray, delta_c: np.ndarray, cov6: np.ndarray, *,
                     chunk: int = 4096) -> np.ndarray:
    """Deformed covariances J Sigma J^T, J = I + sum_k outer(delta_c[k], gradients[:, k]).

    gradients: (M, k, 3) float32; delta_c: (k, 3); cov6: (M, 6) upper triangles.
    Returns (M, 6) float32.
    """
    m, k, _ = gradients.shape
    dt = np.float32
    d = np.asarray(delta_c, dtype=dt)
    mix = np.einsum("ka,bc->kbac", d, np.eye(3, dtype=dt)).reshape(3 * k, 9)
    out = np.empty((m, 6), dtype=dt)
    flat = gradients.reshape(m, 3 * k)
    for s in range(0, m, chunk):
        e = min(s + chunk, m)
        j = np.ascontiguousarray((flat[s:e] @ mix).T)  # (9, n): J - I, row-major (a, b)
        j[0] += 1
        j[4] += 1
        j[8] += 1
        c = np.ascontiguousarray(cov6[s:e].T)
        sig = ((c[0], c[1], c[2]), (c[1], c[3], c[4]), (c[2], c[4], c[5]))
        # A = J Sigma, then Sigma'_ab = sum_c A_ac J_bc
        a = [[j[3 * r] * sig[0][col] + j[3 * r + 1] * sig[1][col] + j[3 * r + 2] * sig[2][col]
              for col in range(3)] for r in range(3)]
        block = np.empty((6, e - s), dtype=dt)
        for i, (r, q) in enumerate(_PAIRS):
            block[i] = a[r][0] * j[3 * q] + a[r][1] * j[3 * q + 1] + a[r][2] * j[3 * q + 2]
        out[s:e] = block.T
    return out
