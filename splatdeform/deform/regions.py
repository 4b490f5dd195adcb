"""Region bookkeeping in model units, before any fit: checks, the metaphors' stacked columns and
the boundary rings (what ``splatdeform select`` shows and what the fit is built from).

Masks are (N,) bool over the model's points; a metaphor (:mod:`splatdeform.deform.metaphor`)
brings its own moving points. Errors are :class:`RegionError` naming the config key the caller
gave the region (``regions.handle``, ``handles[1].region``, ``curve``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splatdeform.deform.handle import AffineFrame
from splatdeform.deform.metaphor import Metaphor
from splatdeform.deform.rings import band_adjacency, neighbours_of, rings
from splatdeform.errors import RegionError
from splatdeform.model import PointModel


@dataclass(frozen=True)
class Group:
    """One metaphor inside a deformation.

    name: its config key (``regions.handle``, ``handles[1]``, ``curve``).
    columns: (start, stop): its columns of delta_c (k rows of delta_c in all).
    rows: (Nm,) int64 positions of its points in ``Deformation.moving_idx``.
    frame: a handle's affine frame (its points then get the handle's 4x4 map verbatim).
    constraints: what the columns of a kind without a moving region were fitted to (the
    control-point pairs' :class:`~splatdeform.deform.points.PointsFit`), else None.
    """

    name: str
    columns: tuple[int, int]
    rows: np.ndarray
    frame: AffineFrame | None = None
    constraints: object | None = None



@dataclass(frozen=True)
class Layout:
    """Where an edit's metaphors sit and the rings they give (no fit yet).

    fixed / moving: (N,) bool. moving_idx: (Nh,) int64. coords: (Nh, k) float64 control
    coordinates, gradients: (Nh, k, 3) float64 (a point's row is zero outside its own
    metaphor's columns). groups: one per metaphor. fixed_rings / moving_rings: ring point
    indices (int64 arrays), ring 1 first. name: what the moving region is called in errors.
    """

    fixed: np.ndarray
    moving: np.ndarray
    moving_idx: np.ndarray
    coords: np.ndarray
    gradients: np.ndarray
    groups: list[Group]
    fixed_rings: list[np.ndarray]
    moving_rings: list[np.ndarray]
    name: str


def check_region_counts(n_fixed: int, n_handle: int, n_overlap: int, n_free: int, *,
                        handle_name: str = "handle") -> None:
    """The one region check, from counts (so the in-memory and the streamed edit, which only
    counts its chunks, say the same line): RegionError for an empty fixed or handle region,
    overlapping regions, or regions that leave no free point. ``n_fixed`` / ``n_handle``:
    points each selects (overlap included); ``n_free``: points neither selects."""
    if n_fixed == 0:
        raise RegionError.at("regions.fixed", "selects no point; widen the fixed region")
    if n_handle == 0:
        raise RegionError.at(f"regions.{handle_name}",
                             f"selects no point; widen the {handle_name} region")
    if n_overlap:
        raise RegionError.at("regions", f"fixed and {handle_name} regions overlap in "
                             f"{n_overlap} points; they must be disjoint")
    if n_free == 0:
        raise RegionError.at("regions", f"fixed and {handle_name} regions cover every point; "
                             "leave a free region between them")


def not_adjacent(key: str, what: str) -> RegionError:
    """The one line for a region none of whose points is adjacent to the free region (a
    separate cluster: no kNN edge or mesh edge reaches a free point). The in-memory rings and
    the streamed border (where such a region has no point near the free region) say it alike."""
    return RegionError.at(key, f"no {what} point is adjacent to the free region (a separate "
                          f"cluster: no neighbour edge reaches a free point, so it has no "
                          f"rings); select {what} points that touch the free region, or raise "
                          "boundary.neighbors")


def check_regions(fixed: np.ndarray, handle: np.ndarray, *, handle_name: str = "handle") -> None:
    """Raise RegionError for empty, overlapping or all-covering regions (fixed, handle:
    (N,) bool masks; :func:`check_region_counts`)."""
    check_region_counts(int(fixed.sum()), int(handle.sum()), int((fixed & handle).sum()),
                        int((~(fixed | handle)).sum()), handle_name=handle_name)


def check_metaphor(fixed: np.ndarray, mph: Metaphor, n: int) -> None:
    """Empty or overlapping the fixed region: one line naming the metaphor's key."""
    mask = np.zeros(n, dtype=bool)
    mask[mph.idx] = True
    if mph.name.startswith("regions.") or " " in mph.name:
        check_regions(fixed, mask, handle_name=short_name(mph.name))
        return
    if not mask.any():
        raise RegionError.at(f"{mph.name}", "selects no point; widen it")
    both = fixed & mask
    if both.any():
        raise RegionError.at(f"{mph.name}", f"overlaps regions.fixed in {int(both.sum())} points; "
                          "they must be disjoint")


def short_name(name: str) -> str:
    """``regions.handle`` -> ``handle`` (check_regions prefixes ``regions.``)."""
    return name[len("regions."):] if name.startswith("regions.") else name


def moving_columns(n_points: int, metaphors: list[Metaphor]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[Group]]:
    """Stack the metaphors' columns: moving_idx (Nh,), coords (Nh, k), gradients (Nh, k, 3)
    and the groups. A point's row is zero outside its own metaphor's columns. One metaphor
    with sorted distinct indices: its own arrays, no copy (a handle's gradients stay the
    broadcast view of its one (4, 3) row)."""
    if len(metaphors) == 1 and _strictly_increasing(metaphors[0].idx):
        mph = metaphors[0]
        idx = np.asarray(mph.idx, dtype=np.int64)
        coords = np.asarray(mph.coords, dtype=np.float64)
        grads = np.asarray(mph.gradients, dtype=np.float64)
        if coords.shape == (idx.size, mph.k) and grads.shape == (idx.size, mph.k, 3):
            return idx, coords, grads, [Group(mph.name, (0, mph.k), np.arange(idx.size),
                                              mph.frame)]
    owner = np.full(n_points, -1, dtype=np.int64)
    for j, mph in enumerate(metaphors):
        taken = owner[mph.idx] >= 0
        if taken.any():
            other = metaphors[int(owner[mph.idx[taken][0]])].name
            raise RegionError.at(f"{mph.name}", f"overlaps {other} in {int(taken.sum())} points; "
                              "moving regions must be disjoint")
        owner[mph.idx] = j
    moving_idx = np.flatnonzero(owner >= 0)
    lookup = np.full(n_points, -1, dtype=np.int64)
    lookup[moving_idx] = np.arange(moving_idx.size)
    k = sum(mph.k for mph in metaphors)
    coords = np.zeros((moving_idx.size, k))
    grads = np.zeros((moving_idx.size, k, 3))
    groups, start = [], 0
    for mph in metaphors:
        rows = lookup[mph.idx]
        coords[rows, start:start + mph.k] = mph.coords
        grads[rows, start:start + mph.k] = mph.gradients
        groups.append(Group(mph.name, (start, start + mph.k), rows, mph.frame))
        start += mph.k
    return moving_idx, coords, grads, groups


def _strictly_increasing(idx: np.ndarray) -> bool:
    """Indices (M,) sorted with no repeats (what ``flatnonzero`` of a mask gives)."""
    idx = np.asarray(idx)
    return idx.ndim == 1 and bool((idx[1:] > idx[:-1]).all())


def layout(model: PointModel, fixed: np.ndarray, metaphors: list[Metaphor], *,
           continuity: int = 2, neighbors: int = 10) -> Layout:
    """Check the regions, stack the metaphors' columns and find the boundary rings: every
    step of :func:`splatdeform.deform.prepare_metaphors` before the fit.

    Raises RegionError when a metaphor is empty, overlaps the fixed region or another
    metaphor, or has no point next to the free region.
    """
    if continuity not in (0, 1, 2):
        raise RegionError.at("boundary.continuity", f"expected 0, 1 or 2, got {continuity}")
    if not metaphors:
        raise RegionError.at("regions", "an edit needs at least one handle or curve")
    n = model.n_points
    for mph in metaphors:
        check_metaphor(fixed, mph, n)
    moving_idx, coords, grads, groups = moving_columns(n, metaphors)
    moving = np.zeros(n, dtype=bool)
    moving[moving_idx] = True
    name = short_name(metaphors[0].name) if len(metaphors) == 1 else "handle"
    check_regions(fixed, moving, handle_name=name)
    adj = band_adjacency(model, fixed, moving, neighbors, continuity + 2)
    fixed_rings, moving_rings = region_rings(adj, fixed, moving, continuity + 1, name)
    if len(metaphors) > 1:
        first_ring = moving_rings[0]
        for mph in metaphors:
            if not np.isin(mph.idx, first_ring, assume_unique=True).any():
                raise RegionError.at(mph.name, "no point of it is adjacent to the free "
                                     "region (is it enclosed by another region or a "
                                     "separate component? raise boundary.neighbors)")
    return Layout(fixed, moving, moving_idx, coords, grads, groups, list(fixed_rings),
                  list(moving_rings), name)


def region_rings(adj, fixed: np.ndarray, moving: np.ndarray, count: int, name: str
                 ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The ``count`` rings of the fixed and the moving region next to the free region (adj: the
    (N, N) adjacency); RegionError when the regions touch each other or one of them has no
    point next to the free region (:func:`not_adjacent`: regions in separate clusters)."""
    free = ~(fixed | moving)
    touching = neighbours_of(adj, moving) & fixed
    if touching.any():
        raise RegionError.at("regions", f"{int(touching.sum())} fixed points are adjacent to "
                             f"{name} points; leave a free region between them")
    fixed_rings = rings(adj, fixed, free, count)
    moving_rings = rings(adj, moving, free, count)
    if fixed_rings[0].size == 0:
        raise not_adjacent("regions.fixed", "fixed")
    if moving_rings[0].size == 0:
        raise not_adjacent(f"regions.{name}", name)
    return fixed_rings, moving_rings
