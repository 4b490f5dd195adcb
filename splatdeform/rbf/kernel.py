"""Radial kernels: phi(r) and its gradient with respect to the evaluation point.

Only the triharmonic kernel phi(r) = r^3 is used (globally supported, third-order energy
minimising). The small table keeps the fitter and the basis generic over the kernel.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np


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
    from scipy.spatial.distance import cdist  # on first use (scipy.spatial: ~0.2 s import)

    r = cdist(np.asarray(x, dtype=np.float64), np.asarray(s, dtype=np.float64))
    return KERNELS[kernel].phi(r)


#: Bytes of one row block of :func:`cubed_distance_rows` (kept in the core's cache while its
#: passes run over it).
BLOCK_BYTES = 1 << 19


def cubed_distance_rows(x: np.ndarray, s: np.ndarray, out: np.ndarray | None = None, *,
                        upper: bool = False, rows: tuple[int, int] | None = None,
                        ) -> Iterator[tuple[int, int, np.ndarray]]:
    """|x_i - s_j|^3 for x (M, 3), s (n, 3) float64, one block of rows at a time: yields
    (first row, end row, block) once each block is filled (a caller uses the block while it
    is still in cache). The blocks are rows of ``out`` (M, n) (rows with C-contiguous
    columns), or of one reused buffer when ``out`` is None (each block is overwritten by the
    next). ``upper`` (s is x, ``out`` given): fill only the upper triangle, the block's columns
    from its first row on (the lower triangle of the Fortran-ordered ``out.T``), diagonal 0.
    ``rows``: (first, end), only these rows of x (one thread's share of ``out``).

    Squared distances come from one small GEMM per block, |x|^2 + |s|^2 - 2 x.s (both sides
    shifted to the mean of s, so no large coordinates cancel), clamped at 0; then sqrt and the
    cube in place: four passes over a cache-sized block and no (M, n) temporary, several times
    faster than ``cdist`` and a cube (the sqrt is most of it: half with ``upper``). The
    rounding of a squared distance is about 1e-16 of the squared extent, far below the dense
    solve's own rounding.
    """
    shift = s.mean(axis=0) if s.shape[0] else np.zeros(3)
    xa = np.empty((x.shape[0], 5))
    xa[:, :3] = x - shift
    xa[:, 3] = np.einsum("ij,ij->i", xa[:, :3], xa[:, :3])
    xa[:, 4] = 1.0
    sb = np.empty((5, s.shape[0]))
    sb[:3] = (s - shift).T
    sb[4] = np.einsum("ij,ij->j", sb[:3], sb[:3])
    sb[:3] *= -2.0
    sb[3] = 1.0
    first, end = (0, x.shape[0]) if rows is None else rows
    step = max(1, BLOCK_BYTES // (8 * max(s.shape[0], 1)))
    tmp = np.empty((max(min(step, end - first), 0), s.shape[0]))
    buf = np.empty_like(tmp) if out is None else None
    for a in range(first, end, step):
        e = min(a + step, end)
        c = a if upper else 0
        blk = buf[: e - a] if buf is not None else out[a:e, c:]
        t = tmp[: e - a, c:]
        np.matmul(xa[a:e], sb[:, c:], out=blk)
        np.maximum(blk, 0.0, out=blk)
        np.sqrt(blk, out=t)
        blk *= t
        if upper:
            blk[np.arange(e - a), np.arange(e - a)] = 0.0
        yield a, e, blk


def cubed_distances(x: np.ndarray, s: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """|x_i - s_j|^3 (M, n) float64 for x (M, 3), s (n, 3) (:func:`cubed_distance_rows`);
    ``out``: a C-ordered (M, n) float64 array to fill."""
    x = np.asarray(x, dtype=np.float64)
    s = np.asarray(s, dtype=np.float64)
    if out is None:
        out = np.empty((x.shape[0], s.shape[0]))
    for _ in cubed_distance_rows(x, s, out):
        pass
    return out
