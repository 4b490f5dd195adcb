"""3D Gaussian splat covariance helpers (3DGS conventions: log scales, quaternion w first)."""

from __future__ import annotations

import numpy as np


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """(M, 4) quaternions (w, x, y, z), any length -> (M, 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.divide(q, norm, out=np.tile([1.0, 0, 0, 0], (q.shape[0], 1)), where=norm > 0)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """(M, 3, 3) proper rotations -> (M, 4) unit quaternions (w, x, y, z), w >= 0."""
    m = np.asarray(r, dtype=np.float64)
    t = np.einsum("mii->m", m)
    cands = np.stack([
        np.stack([1 + t, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0],
                  m[:, 1, 0] - m[:, 0, 1]], -1),
        np.stack([m[:, 2, 1] - m[:, 1, 2], 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                  m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0]], -1),
        np.stack([m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0],
                  1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], m[:, 1, 2] + m[:, 2, 1]], -1),
        np.stack([m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1],
                  1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1),
    ], axis=1)  # (M, 4 candidates, 4); pick the numerically largest
    best = np.argmax(np.stack([1 + t, 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                               1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
                               1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1), axis=1)
    q = cands[np.arange(m.shape[0]), best]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    return q


def scale_rotation_to_factor(scale_log: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(M, 3) log scales and (M, 4) quaternions -> (M, 3, 3) factor R S with Sigma = (RS)(RS)^T."""
    return quaternion_to_matrix(rotation) * np.exp(np.asarray(scale_log, np.float64))[:, None, :]


def covariance_to_scale_rotation(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3, 3) symmetric covariances -> (M, 3) log scales, (M, 4) quaternions (right-handed
    eigenvector frame)."""
    evals, evecs = np.linalg.eigh(cov)
    flip = np.linalg.det(evecs) < 0
    evecs[flip, :, 0] *= -1
    scale_log = 0.5 * np.log(np.maximum(evals, 1e-30))
    return scale_log.astype(np.float32), matrix_to_quaternion(evecs).astype(np.float32)
