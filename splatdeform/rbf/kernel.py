"""Radial kernels: phi(r) and its gradient with respect to the evaluation point.

Only the triharmonic kernel phi(r) = r^3 is used (globally supported, third-order energy
minimising). The small table keeps the fitter and the basis generic over the kernel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.distance import cdist


def triharmonic(r: np.ndarray) -> np.ndarray:
    """phi(r) = r^3 for an array of distances ``r`` (any shape, float64)."""
    return r * r * r


def triharmonic_gradient_factor(r: np.ndarray) -> np.ndarray:
    """g(r) such that grad_x phi(|x - s|) = g(r) (x - s); for r^3 it is 3 r."""
    return 3.0 * r


@dataclass(frozen=True)
class Kernel:
    """A radial kernel: ``phi(r)`` and ``gradient_factor(r)`` with grad phi = factor * (x - s)."""

    name: str
    phi: Callable[[np.ndarray], np.ndarray]
    gradient_factor: Callable[[np.ndarray], np.ndarray]


KERNELS: dict[str, Kernel] = {
    "triharmonic": Kernel("triharmonic", triharmonic, triharmonic_gradient_factor),
}


def phi(r: np.ndarray) -> np.ndarray:
    """The triharmonic kernel r^3 (alias of :func:`triharmonic`)."""
    return triharmonic(np.asarray(r, dtype=np.float64))


def phi_gradient(x: np.ndarray, s: np.ndarray) -> np.ndarray:
    """grad_x phi(|x - s|) = 3 |x - s| (x - s).

    x: (..., 3) evaluation points, s: (..., 3) centers (broadcast). Returns (..., 3) float64.
    """
    diff = np.asarray(x, dtype=np.float64) - np.asarray(s, dtype=np.float64)
    r = np.linalg.norm(diff, axis=-1, keepdims=True)
    return 3.0 * r * diff


def kernel_matrix(x: np.ndarray, s: np.ndarray, kernel: str = "triharmonic") -> np.ndarray:
    """phi(|x_i - s_j|) for points x (M, 3) and centers s (n, 3): (M, n) float64."""
    r = cdist(np.asarray(x, dtype=np.float64), np.asarray(s, dtype=np.float64))
    return KERNELS[kernel].phi(r)
