"""Farthest point sampling with a deterministic start.

The first pick is the point farthest from the centroid; every next pick is the point farthest from
all picks so far. Ties go to the lowest index (``np.argmax``). Sampling stops early when the next
largest distance is 0 (only duplicates of picked points remain).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from splatdeform.errors import InputError


def squared_distances(coords: np.ndarray, i: int, out: np.ndarray,
                      tmp: np.ndarray) -> np.ndarray:
    """out (M,) <- squared distances of the points coords (3, M) (one contiguous row per
    coordinate) to point i; tmp (M,) is scratch. Returns out."""
    np.subtract(coords[0], coords[0, i], out=out)
    np.multiply(out, out, out=out)
    for c in (1, 2):
        np.subtract(coords[c], coords[c, i], out=tmp)
        np.multiply(tmp, tmp, out=tmp)
        out += tmp
    return out


def iter_farthest_points(points: np.ndarray) -> Iterator[int]:
    """Yield indices of ``points`` (M, 3) in farthest-point order, lazily.

    Each step costs O(M); the generator stops after at most M picks or at the first duplicate.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[0] == 0:
        return
    diff = pts - pts.mean(axis=0)
    nxt = int(np.argmax(np.einsum("ij,ij->i", diff, diff)))
    coords = np.ascontiguousarray(pts.T)  # (3, M): one contiguous row per coordinate
    dist2 = np.full(pts.shape[0], np.inf)
    d2 = np.empty(pts.shape[0])
    tmp = np.empty(pts.shape[0])
    while True:
        yield nxt
        np.minimum(dist2, squared_distances(coords, nxt, d2, tmp), out=dist2)
        nxt = int(np.argmax(dist2))
        if not dist2[nxt] > 0.0:
            return


def farthest_point_order(points: np.ndarray, max_count: int | None = None) -> np.ndarray:
    """Indices of up to ``max_count`` points of ``points`` (M, 3) in farthest-point order.

    Returns (n,) int64 with n <= min(M, max_count); fewer when only duplicates remain.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points: expected shape (M, 3), got {pts.shape}")
    limit = pts.shape[0] if max_count is None else min(int(max_count), pts.shape[0])
    out = []
    if limit <= 0:
        return np.zeros(0, dtype=np.int64)
    for idx in iter_farthest_points(pts):
        out.append(idx)
        if len(out) >= limit:
            break
    return np.asarray(out, dtype=np.int64)
