"""Config-free geometry of the streaming border set: voxel keys and their neighbourhoods,
distances to the other label, k-th-neighbour distances, and the handle frame from streamed
moments (the out-of-core path's counterparts of :func:`splatdeform.deform.handle.handle_frame`
and the kNN scale). The passes over a file that use them live in
:mod:`splatdeform.edit.stream.plan`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from splatdeform.deform.handle import AffineFrame
from splatdeform.errors import RegionError
from splatdeform.interrupts import knn_query


def initial_radius(sample: np.ndarray, n: int, neighbors: int, rings: int,
                   lo: np.ndarray, hi: np.ndarray) -> float:
    """The border radius R from the k-th-neighbour distance of a sample (M, 3) of n points
    scaled to the full density (surface scaling), with the (rings + 1) r < R/2 rule and a
    factor 2 of slack; within [1e-9, 1] times the diagonal of the box [lo, hi]."""
    m = sample.shape[0]
    k = min(neighbors, m - 1)
    diag = float(np.linalg.norm(hi - lo)) or 1.0
    if k < 1:
        return diag
    dist, _ = knn_query(cKDTree(sample), sample, k=k + 1)
    r_sample = float(np.quantile(dist[:, -1], 0.95))
    r = r_sample * math.sqrt(m / max(n, 1))
    return min(max(3.5 * (rings + 1) * r, 1e-9 * diag), diag)


def voxel_keys(pos: np.ndarray, lo: np.ndarray, h: float, dims: np.ndarray) -> np.ndarray:
    """(N,) int64 keys of the voxels of edge ``h`` holding points (N, 3) of a grid of ``dims``
    (3,) voxels from ``lo``."""
    ijk = np.minimum(((pos - lo) / h).astype(np.int64), dims - 1)
    return (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]


def near_voxels(keys: np.ndarray, others: np.ndarray, dims: np.ndarray,
                reach: int = 2) -> np.ndarray:
    """The voxels of ``keys`` (sorted unique) within Chebyshev distance ``reach`` of a voxel of
    ``others`` (sorted unique); memory O(len(keys)), one lookup per offset."""
    i = keys // (dims[1] * dims[2])
    j = (keys // dims[2]) % dims[1]
    k = keys % dims[2]
    hit = np.zeros(keys.shape, dtype=bool)
    steps = range(-reach, reach + 1)
    for di in steps:
        for dj in steps:
            for dk in steps:
                a, b, c = i + di, j + dj, k + dk
                ok = (a >= 0) & (a < dims[0]) & (b >= 0) & (b < dims[1]) & (c >= 0) & (c < dims[2])
                hit[ok] |= in_sorted((a[ok] * dims[1] + b[ok]) * dims[2] + c[ok], others)
    return keys[hit]


def merge_keys(parts: list[np.ndarray], new: np.ndarray) -> list[np.ndarray]:
    """Append sorted unique keys; consolidate when the pending parts outgrow the merged set
    (chunks of a shuffled scan each touch most voxels: without this, memory grows with N)."""
    parts = parts + [new]
    if len(parts) > 2 and sum(p.size for p in parts[1:]) > max(parts[0].size, 1 << 16):
        parts = [np.unique(np.concatenate(parts))]
    return parts


def in_sorted(keys: np.ndarray, table: np.ndarray) -> np.ndarray:
    """(N,) bool: which ``keys`` are in the sorted array ``table``."""
    if table.size == 0:
        return np.zeros(keys.shape, dtype=bool)
    at = np.minimum(np.searchsorted(table, keys), table.size - 1)
    return table[at] == keys


def distance_to_other(pos: np.ndarray, free: np.ndarray, radius: float) -> np.ndarray:
    """(S,) distance of each point (S, 3) to the nearest point on the other side of ``free``
    (S,) bool (free vs region), inf beyond ``radius`` or when one side is empty."""
    dist = np.full(pos.shape[0], np.inf)
    if free.any() and (~free).any():
        dist[~free] = knn_query(cKDTree(pos[free]), pos[~free], k=1,
                                distance_upper_bound=radius)[0]
        dist[free] = knn_query(cKDTree(pos[~free]), pos[free], k=1,
                               distance_upper_bound=radius)[0]
    return dist


def kth_distance(points: np.ndarray, k: int, block: int = 500_000) -> np.ndarray:
    """(M,) distance of each point to its k-th nearest other point (within ``points``)."""
    tree = cKDTree(points)
    k = min(k, points.shape[0] - 1)
    out = np.empty(points.shape[0])
    for a in range(0, points.shape[0], block):
        out[a:a + block] = knn_query(tree, points[a:a + block], k=k + 1)[0][:, -1]
    return out


class Moments:
    """Streaming first and second moments of points (about a reference point ``ref`` (3,))."""

    def __init__(self, ref: np.ndarray) -> None:
        self.ref = np.asarray(ref, dtype=np.float64)
        self.n = 0
        self.s1 = np.zeros(3)
        self.s2 = np.zeros((3, 3))

    def add(self, points: np.ndarray) -> None:
        d = points - self.ref
        self.n += points.shape[0]
        self.s1 += d.sum(axis=0)
        self.s2 += d.T @ d

    def centroid_and_axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centroid (3,), singular values (3,) of the centred points, vt (3, 3) rows =
        principal axes, largest first): what an SVD of the centred points gives."""
        mean = self.s1 / self.n
        cov = self.s2 - self.n * np.outer(mean, mean)
        values, vectors = np.linalg.eigh((cov + cov.T) / 2)
        order = np.argsort(values)[::-1]
        return self.ref + mean, np.sqrt(np.maximum(values[order], 0.0)), vectors[:, order].T


def frame_from_moments(moments: Moments,
                       extent_of: Callable[[np.ndarray, np.ndarray], np.ndarray]
                       ) -> AffineFrame:
    """The handle frame of :func:`splatdeform.deform.handle.handle_frame` from streamed moments;
    ``extent_of(centroid, vt)`` -> (3,) largest |(p - centroid) . axis| over the handle."""
    centroid, sv, vt = moments.centroid_and_axes()
    if sv[0] <= 0 or sv[1] <= 1e-6 * sv[0]:
        raise RegionError("regions.handle: the handle points are (nearly) collinear or a single "
                          "point; an affine handle needs points spanning at least a plane")
    extent = extent_of(centroid, vt)
    extent = np.where(extent > 1e-3 * extent[0], extent, extent[0])
    axes = vt * extent[:, None]
    if np.linalg.det(vt) < 0:
        axes[2] *= -1
    control = np.vstack([centroid, centroid + axes])
    system = np.vstack([control.T, np.ones(4)])
    return AffineFrame(control_points=control, inverse=np.linalg.inv(system))
