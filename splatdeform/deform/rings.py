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

from splatdeform.deform.cells import (
    Cells,
    GridTooFine,
    SubsetKnn,
    kth_distances,
    levels_around,
)
from splatdeform.errors import RegionError
from splatdeform.geometry import bounds
from splatdeform.interrupts import knn_query
from splatdeform.model import PointModel


def knn_edges(positions: np.ndarray, k: int, subset: np.ndarray | None = None) -> np.ndarray:
    """Directed edges (E, 2) int64 from each point (or each point of ``subset``) to its k
    nearest other points. positions: (N, 3)."""
    n = positions.shape[0]
    k = int(min(k, n - 1))
    if k <= 0:
        return np.empty((0, 2), dtype=np.int64)
    tree = cKDTree(positions)
    query = positions if subset is None else positions[subset]
    _, nbr = knn_query(tree, query, k=k + 1)
    src = np.arange(n) if subset is None else np.asarray(subset)
    src = np.repeat(src, k + 1)
    dst = nbr.reshape(-1)
    keep = (dst != src) & (dst < n)
    return np.stack([src[keep], dst[keep]], axis=1)


#: Points sampled (seeded) to estimate the kNN radius that sizes the border band.
_SPACING_SAMPLE = 4000
_BAND_SAFETY = 2.0
#: Cells of the band grid around the border cells whose points the kd-tree holds.
_REACH = 2


def border_band(positions: np.ndarray, labels: np.ndarray, radius: float) -> np.ndarray:
    """Mask (N,) of points within about ``radius`` of a point with another label.

    labels: (N,) small ints (free / fixed / moving). Points are hashed into cells of size
    ``radius``; a cell is on the border when its 3x3x3 neighbourhood holds two or more labels,
    so every point within ``radius`` of another label is in the band (and some a little
    farther). No neighbour search, and no sort when the grid is small (see
    :class:`splatdeform.deform.cells.Cells`).
    """
    try:
        cells = Cells(positions, radius)
    except GridTooFine:  # a radius far below the model's extent: every point
        return np.ones(positions.shape[0], dtype=bool)
    return cells.label_border(labels)[cells.cell]


def sample_indices(n: int, seed: int = 0) -> np.ndarray:
    """The seeded sample (M,) of point indices whose k-th-neighbour distances size the band."""
    if n <= _SPACING_SAMPLE:
        return np.arange(n)
    return np.random.default_rng(seed).choice(n, _SPACING_SAMPLE, replace=False)


def knn_radius(positions: np.ndarray, k: int, seed: int = 0, box: tuple | None = None
               ) -> tuple[float, cKDTree | None]:
    """A high quantile of the distance to the k-th nearest neighbour over a seeded sample: the
    whole-model tree's value, from trees over the cells around the sample when those hold a
    small share of the model; with the whole-model tree when one was built (else None)."""
    n = positions.shape[0]
    idx = sample_indices(n, seed)
    k1 = min(k + 1, n)
    sample = positions[idx]
    if idx.size > k1:  # first guess: the sample's own spacing scaled to the whole (surfaces)
        own = knn_query(cKDTree(sample), sample, k=k1)[0][:, -1]
        guess = float(np.quantile(own, 0.9)) * (idx.size / n) ** 0.5  # ~90% certified
    else:
        lo, hi = bounds(positions) if box is None else box
        guess = float(np.linalg.norm(hi - lo))
    dist, whole = kth_distances(positions, idx, k1, guess, box=box)
    return float(np.quantile(dist, 0.999)), whole


def border_knn_adjacency(positions: np.ndarray, labels: np.ndarray, neighbors: int,
                         depth: int, stats: dict | None = None) -> sp.csr_matrix:
    """Symmetric (N, N) kNN adjacency holding only the edges of points near the label borders
    (:func:`border_knn_edges` both ways)."""
    edges = border_knn_edges(positions, labels, neighbors, depth, stats)
    return _symmetric(edges, positions.shape[0])


def border_knn_edges(positions: np.ndarray, labels: np.ndarray, neighbors: int,
                     depth: int, stats: dict | None = None) -> np.ndarray:
    """Directed kNN edges (E, 2) int64 of the points near the label borders, no self-loops.

    The rings (``depth`` of them) and the region checks only look at edges within a few hops of
    where the free, fixed and moving regions meet, so only those points are queried instead of
    the whole model: the candidates in a thin voxel band around the borders (two kNN radii);
    the seeds among them whose k nearest neighbours hold another label, with those neighbours;
    then ``depth + 1`` hops of kNN expansion from the seeds, so every ring point and every
    neighbour of one has its own kNN list, whatever the local density. Edges that exist only
    because a point far from every border lists a ring point among its neighbours (a lone
    outlier) are the one thing not searched; the tests check equality with the whole-model
    graph's rings on every shared scan.

    The kd-tree holds the band's points and two cells around it, not the whole model; every
    answer is the whole-model tree's (see :class:`splatdeform.deform.cells.SubsetKnn`).
    ``stats``, when given, receives the work counts: ``tree_points`` (points in the kd-tree),
    ``queried`` (points queried) and ``fallback`` (queries the whole-model tree answered).
    """
    n = positions.shape[0]
    k = int(min(neighbors, n - 1))
    if k <= 0:
        return np.empty((0, 2), dtype=np.int64)
    lo, hi = bounds(positions)
    radius, tree = knn_radius(positions, k, box=(lo, hi))
    extent = float((hi - lo).max())
    search: SubsetKnn | None = None
    frontier = None  # every point, unless the band below is found
    if radius > 0 and 2 * radius * _BAND_SAFETY < extent:
        try:
            cells = Cells(positions, 2 * radius * _BAND_SAFETY, (lo, hi))
        except GridTooFine:
            cells = None
        if cells is not None:
            core = cells.label_border(labels)
            frontier = np.flatnonzero(core[cells.cell])
            if tree is None:
                search = SubsetKnn(positions, cells, levels_around(cells, core, _REACH),
                                   _REACH)
            if search is not None and 2 * search.subset.size > n:  # most of the model
                search = None
    if frontier is None:
        frontier = np.arange(n)
    if search is not None:
        query = search.query
    else:
        tree = cKDTree(positions) if tree is None else tree

        def query(idx: np.ndarray, k1: int) -> np.ndarray:
            return knn_query(tree, positions[idx], k=k1)[1]
    queried = np.zeros(n, dtype=bool)
    sources, targets = [], []
    for hop in range(depth + 2):
        if frontier.size == 0:
            break
        nbr = query(frontier, k + 1)
        queried[frontier] = True
        sources.append(np.repeat(frontier, k + 1))
        targets.append(nbr.reshape(-1))
        valid = nbr < n
        if hop == 0:  # seeds: candidates with a neighbour of another label, and that neighbour
            cross = valid & (labels[np.minimum(nbr, n - 1)] != labels[frontier][:, None])
            reached = np.concatenate([frontier[cross.any(axis=1)], nbr[cross]])
        else:
            reached = nbr[valid]
        reached = np.unique(reached)
        frontier = reached[~queried[reached]]
    if stats is not None:
        stats.update(tree_points=n if search is None else search.subset.size,
                     queried=int(queried.sum()),
                     fallback=0 if search is None else search.fallback)
    if not sources:  # no label border at all (regions in separate clusters): no edges
        return np.empty((0, 2), dtype=np.int64)
    src = np.concatenate(sources)
    dst = np.concatenate(targets)
    keep = (dst != src) & (dst < n)
    return np.stack([src[keep], dst[keep]], axis=1)


def _symmetric(edges: np.ndarray, n: int) -> sp.csr_matrix:
    """(N, N) bool csr, no diagonal: ``edges`` (E, 2) both ways, self-loops dropped first
    (setting an N-long diagonal afterwards cost more than the whole band's graph)."""
    edges = edges[edges[:, 0] != edges[:, 1]]
    data = np.ones(len(edges), dtype=bool)
    adj = sp.coo_matrix((data, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    return (adj + adj.T).tocsr()


class BandAdjacency:
    """The symmetric (N, N) adjacency of :func:`_symmetric` kept over the M points that have
    an edge (the border band): ``nodes`` (M,) sorted global indices, ``local`` (M, M) bool
    csr. :func:`neighbours_of` and :func:`rings` give what they give on the (N, N) matrix
    (the same rows, so the same int8 sums), with no N-long sparse product or mask per ring."""

    def __init__(self, edges: np.ndarray, n: int) -> None:
        self.n = n
        edges = edges[edges[:, 0] != edges[:, 1]]
        seen = np.zeros(n, dtype=bool)
        seen[edges.ravel()] = True
        self.nodes = np.flatnonzero(seen)
        lookup = np.empty(n, dtype=np.int32 if self.nodes.size < 2**31 else np.int64)
        lookup[self.nodes] = np.arange(self.nodes.size)
        self.local = _symmetric(lookup[edges].astype(np.int64), self.nodes.size)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n, self.n)

    def neighbours_of(self, mask: np.ndarray) -> np.ndarray:
        """Mask (N,) of points adjacent to any point of ``mask`` (N,)."""
        out = np.zeros(self.n, dtype=bool)
        out[self.nodes] = neighbours_of(self.local, mask[self.nodes])
        return out

    def rings(self, region: np.ndarray, free: np.ndarray, count: int) -> list[np.ndarray]:
        """:func:`rings` on the band: global index arrays (int64), ring 1 first."""
        return [self.nodes[r] for r in rings(self.local, region[self.nodes],
                                             free[self.nodes], count)]


def band_adjacency(model: PointModel, fixed: np.ndarray, moving: np.ndarray,
                   neighbors: int = 10, depth: int = 3) -> sp.csr_matrix | BandAdjacency:
    """:func:`region_adjacency` for the rings alone: the kNN graph as a
    :class:`BandAdjacency` (mesh edges as the (N, N) matrix)."""
    if model.faces is not None and model.n_faces:
        return adjacency(model, neighbors)
    labels = fixed.astype(np.int8) + 2 * moving.astype(np.int8)
    edges = border_knn_edges(model.positions, labels, neighbors, depth)
    return BandAdjacency(edges, model.n_points)


def region_adjacency(model: PointModel, fixed: np.ndarray, moving: np.ndarray,
                     neighbors: int = 10, depth: int = 3) -> sp.csr_matrix:
    """The adjacency the rings need: mesh edges when the model has faces, else the kNN graph
    restricted to the band where the regions meet (see :func:`border_knn_adjacency`)."""
    if model.faces is not None and model.n_faces:
        return adjacency(model, neighbors)
    labels = fixed.astype(np.int8) + 2 * moving.astype(np.int8)
    return border_knn_adjacency(model.positions, labels, neighbors, depth)


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
    return _symmetric(edges, n)


def neighbours_of(adj, mask: np.ndarray) -> np.ndarray:
    """Mask (N,) of points adjacent to any point of ``mask``."""
    if isinstance(adj, BandAdjacency):
        return adj.neighbours_of(mask)
    return (adj @ mask.astype(np.int8)) > 0


def rings(adj, region: np.ndarray, free: np.ndarray, count: int) -> list[np.ndarray]:
    """The first ``count`` rings of ``region`` next to ``free``: list of index arrays (int64)."""
    if isinstance(adj, BandAdjacency):
        return adj.rings(region, free, count)
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
        raise RegionError.at("regions", f"{int(touching.sum())} fixed points are adjacent to "
                          f"{handle_name} points; leave a free region between them")
    fixed_rings = rings(adj, fixed, free, count)
    handle_rings = rings(adj, handle, free, count)
    if fixed_rings[0].size == 0:
        raise RegionError.at("regions.fixed", "no fixed point is adjacent to the free region (is "
                          "it a separate component? raise boundary.neighbors)")
    if handle_rings[0].size == 0:
        raise RegionError.at(f"regions.{handle_name}", f"no {handle_name} point is adjacent to the "
                          "free region (is it a separate component? raise boundary.neighbors)")
    return fixed_rings, handle_rings
