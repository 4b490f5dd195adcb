"""Adjacency and boundary rings.

Adjacency is the mesh edge graph when the model has faces (vertices used by no face are joined
to their k nearest neighbours so they are not isolated), else the symmetric k-nearest-neighbour
graph. Ring 1 of a region = its points adjacent to the free region; ring i = its points adjacent
to ring i-1 and not yet taken.

Disconnected components: rings only grow along the graph, so a component that holds no free
point contributes no constraint. Free points in a component that touches neither region still
move with the (globally defined) space deformation, which is smooth everywhere.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .errors import RegionError
from .model import PointModel


def knn_edges(positions: np.ndarray, k: int, subset: np.ndarray | None = None) -> np.ndarray:
    """Directed edges (E, 2) int64 from each point (or each point of ``subset``) to its k
    nearest other points. positions: (N, 3)."""
    n = positions.shape[0]
    k = int(min(k, n - 1))
    if k <= 0:
        return np.empty((0, 2), dtype=np.int64)
    tree = cKDTree(positions)
    query = positions if subset is None else positions[subset]
    _, nbr = tree.query(query, k=k + 1, workers=-1)
    src = np.arange(n) if subset is None else np.asarray(subset)
    src = np.repeat(src, k + 1)
    dst = nbr.reshape(-1)
    keep = (dst != src) & (dst < n)
    return np.stack([src[keep], dst[keep]], axis=1)


def adjacency(model: PointModel, neighbors: int = 10) -> sp.csr_matrix:
    """Symmetric (N, N) boolean adjacency: mesh edges if the model has faces, else kNN."""
    n = model.n_points
    if model.faces is not None and model.n_faces:
        f = model.faces
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        used = np.zeros(n, dtype=bool)
        used[f.ravel()] = True
        if not used.all():
            edges = np.concatenate([edges, knn_edges(model.positions, neighbors,
                                                     np.flatnonzero(~used))])
    else:
        edges = knn_edges(model.positions, neighbors)
    data = np.ones(len(edges), dtype=bool)
    adj = sp.coo_matrix((data, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    adj = (adj + adj.T).tocsr()
    adj.setdiag(False)
    adj.eliminate_zeros()
    return adj


def neighbours_of(adj: sp.csr_matrix, mask: np.ndarray) -> np.ndarray:
    """Mask (N,) of points adjacent to any point of ``mask``."""
    return (adj @ mask.astype(np.int8)) > 0


def rings(adj: sp.csr_matrix, region: np.ndarray, free: np.ndarray, count: int) -> list[np.ndarray]:
    """The first ``count`` rings of ``region`` next to ``free``: list of index arrays (int64)."""
    taken = np.zeros_like(region)
    frontier = free
    out = []
    for _ in range(count):
        ring = neighbours_of(adj, frontier) & region & ~taken
        out.append(np.flatnonzero(ring))
        taken |= ring
        frontier = ring
    return out


def boundary_rings(adj: sp.csr_matrix, fixed: np.ndarray, handle: np.ndarray, count: int,
                   handle_name: str = "handle") -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Rings of the fixed and handle regions next to the free region, with checks.

    Raises RegionError when the regions touch each other directly (no free region between them)
    or when a region does not border the free region at all.
    """
    free = ~(fixed | handle)
    touching = neighbours_of(adj, handle) & fixed
    if touching.any():
        raise RegionError(f"regions: {int(touching.sum())} fixed points are adjacent to "
                          f"{handle_name} points; leave a free region between them")
    fixed_rings = rings(adj, fixed, free, count)
    handle_rings = rings(adj, handle, free, count)
    if fixed_rings[0].size == 0:
        raise RegionError("regions.fixed: no fixed point is adjacent to the free region (is "
                          "it a separate component? raise boundary.neighbors)")
    if handle_rings[0].size == 0:
        raise RegionError(f"regions.{handle_name}: no {handle_name} point is adjacent to the "
                          "free region (is it a separate component? raise boundary.neighbors)")
    return fixed_rings, handle_rings
