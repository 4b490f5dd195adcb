"""Thinning of boundary rings to a well-spread subset of fit constraints.

On point clouds and splats a kNN ring is a thick, noisy shell: hundreds of nearly redundant
points per patch, all with (nearly) the same prescribed value. The fit only needs a well-spread
subset of each ring; the dropped ring points are still fixed or handle points, so they still get
their prescribed values exactly (they never go through the field).

Per ring, from its own points only (so the in-memory and the streaming path, which find the same
rings, keep the same subset):

- local spacing s: the median distance of a ring point to its nearest other ring point;
- ring width W: the median spread across the ring of each point's 2k nearest ring points
  (k = ``boundary.neighbors``; second principal axis, :func:`ring_width`), never below s.

The ring is then voxel-thinned at cell size ``factor * max(W, SPACING_FLOOR * s)``: in each
occupied cell the point nearest the cell's centre is kept (ties: the lowest index). A thick
shell keeps about one point per W-sized cell; a mesh ring one vertex wide (W about its edge
length) keeps about one point in :data:`SPACING_FLOOR` (the field is smooth along the ring at
the scale of a few vertices: the kept ones still pin the dropped ones, checked by ``auto``).
A ring whose cells would be wider than :data:`COARSE_CELL` of the extent of all the ring
points is thinned at that cell instead (the field changes within one wider cell: the solve
through it would miss most dropped points), or kept whole where the ring set is small
(:func:`thin_rings`). The grid starts at the ring's lowest corner; everything is deterministic
and independent of the order of the ring's points except for exact ties.

Every dropped point is still checked: ``fit.method: auto`` adds the dropped points its solve
misses by more than its boundary factor of tolerances and solves again
(:mod:`splatdeform.rbf.auto`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Rings with fewer points are kept whole (nothing to gain, and too few for the statistics).
MIN_RING = 32
#: Largest cell, as a fraction of the bounding-box diagonal of all the ring points; a wider one
#: is cut to it. Measured (``benchmarks/fit_table.py``): the 3DGS tile's cells are 0.055-0.084
#: of it and the dense solve through its thinned rings missed 61% of the dropped points by more
#: than 10 tolerances; every other thinned scene's are at most 0.03 of it, with at most 6%
#: missed (most none). (Rings with wider cells used to be kept whole: the 14k SH3 tile
#: stand-in's 2,187 ring points then took a dense solve through all, 0.11 s; thinned at this
#: cell and completed by ``auto``'s retries, 825 points, 0.03 s.)
COARSE_CELL = 0.04
#: Least cell, in ring spacings s: a ring one point wide (mesh rings) keeps about one point in
#: this many along it. Measured on the Igea mesh stand-in (``data_tools/standins.py``, 2,754
#: ring points): cells of 1 / 2 / 3 / 4 spacings keep 2,248 / 1,411 / 955 / 723 points, whose
#: dense solve misses the dropped ones by at most 1.0 / 2.1 / 3.6 / 8.0 tolerances.
SPACING_FLOOR = 2.0


def ring_width(points: np.ndarray, neighbors: int) -> tuple[float, float]:
    """(width W, median spacing s) of one ring's points (M, 3) float64, M >= 2.

    Around each ring point, the covariance of its 2k nearest ring points has the ring's
    direction as its largest axis; the second is across the ring (a uniform spread of width w
    has variance w^2 / 12), so W = median sqrt(12 lambda_2), never below the spacing s (the
    median distance to the nearest other ring point). A ring one point wide has lambda_2 about
    0 and W = s; a thick shell has W of the order of its kNN neighbourhood. (The cell's floor
    of :data:`SPACING_FLOOR` spacings is :func:`thin_ring`'s.)
    """
    k = int(min(max(2 * neighbors, 4), points.shape[0] - 1))
    dist, nbr = cKDTree(points).query(points, k=k + 1)
    spacing = float(np.median(dist[:, 1]))
    lam = middle_eigenvalues(_neighbourhood_covariances(points, nbr))
    width = float(np.median(np.sqrt(12.0 * np.maximum(lam, 0.0))))
    return max(width, spacing), spacing


def _neighbourhood_covariances(points: np.ndarray, nbr: np.ndarray) -> tuple[np.ndarray, ...]:
    """The six distinct entries (xx, yy, zz, xy, xz, yz), each (M,), of the covariance of each
    point's neighbours ``points[nbr]`` (nbr (M, K) indices): from one gather per coordinate
    (relative to the point itself, so no large coordinates cancel), three sums and six row
    dot products (a batched einsum over (M, K, 3) and its centring took 3x as long)."""
    count = nbr.shape[1]
    rel = []
    for c in range(3):
        coord = np.ascontiguousarray(points[:, c])
        rel.append(coord[nbr] - coord[:, None])          # (M, K)
    mean = [r.sum(axis=1) / count for r in rel]

    def entry(a: int, b: int) -> np.ndarray:
        return np.einsum("mk,mk->m", rel[a], rel[b]) / count - mean[a] * mean[b]

    return entry(0, 0), entry(1, 1), entry(2, 2), entry(0, 1), entry(0, 2), entry(1, 2)


def middle_eigenvalues(cov: tuple[np.ndarray, ...]) -> np.ndarray:
    """The middle eigenvalue (M,) of each symmetric 3x3 matrix given by its six entries
    (xx, yy, zz, xy, xz, yz), each (M,), in closed form (the trigonometric solution of the
    characteristic cubic: eigenvalues q + 2 p cos(phi + 2 pi j / 3)); the middle one is the
    trace less the largest and the smallest."""
    xx, yy, zz, xy, xz, yz = cov
    q = (xx + yy + zz) / 3.0
    off = xy * xy + xz * xz + yz * yz
    a, b, c = xx - q, yy - q, zz - q
    p = np.sqrt((a * a + b * b + c * c + 2.0 * off) / 6.0)
    det = a * (b * c - yz * yz) - xy * (xy * c - yz * xz) + xz * (xy * yz - b * xz)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(p > 0, det / (2.0 * p * p * p), 0.0)
    phi = np.arccos(np.clip(r, -1.0, 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return 3.0 * q - largest - smallest


def thin_ring(points: np.ndarray, neighbors: int, factor: float,
              largest_cell: float = np.inf, coarse_whole: bool = False) -> np.ndarray:
    """Indices (K,) int64, ascending, of the kept points of one ring (M, 3) (all when
    ``factor`` <= 0 or the ring is small): cells of ``factor`` times the ring's width, at least
    :data:`SPACING_FLOOR` spacings, at most ``largest_cell`` (``coarse_whole``: a ring whose
    cell would be wider keeps every point instead)."""
    pts = np.asarray(points, dtype=np.float64)
    m = pts.shape[0]
    if factor <= 0 or m < MIN_RING:
        return np.arange(m, dtype=np.int64)
    width, spacing = ring_width(pts, neighbors)
    cell = factor * max(width, SPACING_FLOOR * spacing)
    if coarse_whole and cell > largest_cell:
        return np.arange(m, dtype=np.int64)
    cell = min(cell, largest_cell)
    if not cell > 0:
        return np.arange(m, dtype=np.int64)
    rel = (pts - pts.min(axis=0)) / cell
    ijk = np.floor(rel).astype(np.int64)
    off = rel - (ijk + 0.5)
    d2 = np.einsum("ij,ij->i", off, off)
    dims = ijk.max(axis=0) + 1
    keys = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.lexsort((np.arange(m), d2, keys))  # by cell, then distance to centre, then index
    first = np.ones(m, dtype=bool)
    first[1:] = keys[order][1:] != keys[order][:-1]
    return np.sort(order[first]).astype(np.int64)


def thin_rings(positions: np.ndarray, rings: list[np.ndarray], neighbors: int,
               factor: float) -> np.ndarray:
    """Mask (sum of ring sizes,) bool over the concatenated rings: the kept constraints.

    positions: (N, 3) of the model; rings: index arrays into it, in constraint order.
    Rings totalling so few points that ``fit.method: auto`` solves through every one of them
    (:data:`splatdeform.rbf.auto.TINY_DENSE`) are kept whole: thinning them would cost as much
    as that solve. No cell is wider than :data:`COARSE_CELL` of the extent of all the ring
    points; a ring whose cell would be is thinned at that cell, except where the solve through
    every ring point is predicted to take at most :data:`splatdeform.rbf.auto.SMALL_DENSE`
    (then it is kept whole: the solve through its capped cells still misses so many dropped
    points that ``auto``'s retries cost more than they save; measured on the 6,831-splat SH3
    tile, 1,426 ring points: 545 kept, two retries, then the solve through all).
    """
    from splatdeform.rbf.auto import SMALL_DENSE, TINY_DENSE, dense_seconds

    total = sum(int(ring.size) for ring in rings)
    predicted = dense_seconds(total, 1)
    if predicted <= TINY_DENSE:
        return np.ones(total, dtype=bool)
    every = positions[np.concatenate(rings)]
    largest = COARSE_CELL * float(np.linalg.norm(every.max(axis=0) - every.min(axis=0)))
    whole = predicted <= SMALL_DENSE  # a coarse ring is kept whole (else thinned at ``largest``)
    parts = []
    for ring in rings:
        keep = np.zeros(ring.size, dtype=bool)
        if ring.size:
            keep[thin_ring(positions[ring], neighbors, factor, largest, whole)] = True
        parts.append(keep)
    return np.concatenate(parts) if parts else np.zeros(0, dtype=bool)
