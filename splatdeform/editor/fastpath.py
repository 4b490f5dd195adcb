"""Symmetric 3x3 packing for the editor's per-frame covariances: the 6 upper-triangle entries
(xx, xy, xz, yy, yz, zz) that :func:`splatdeform.deform.arrays.covariance_frame` deforms."""

from __future__ import annotations

import numpy as np

TRIU = np.array([0, 1, 2, 4, 5, 8])


def triu6(cov: np.ndarray) -> np.ndarray:
    """(N, 3, 3) symmetric -> (N, 6) float32 upper triangle (xx, xy, xz, yy, yz, zz)."""
    return np.ascontiguousarray(cov.reshape(-1, 9)[:, TRIU], dtype=np.float32)


def full_from_triu6(c6: np.ndarray) -> np.ndarray:
    """(N, 6) upper triangle -> (N, 3, 3) symmetric, same dtype."""
    c6 = np.asarray(c6)
    xx, xy, xz, yy, yz, zz = c6.T
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1),
                     np.stack([xz, yz, zz], -1)], axis=1)
