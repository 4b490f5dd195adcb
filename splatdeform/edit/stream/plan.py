"""The streaming first passes: bounding box, regions, border gathering, rings and the fit.

Only what the rings and the fit need is ever held whole:
- labels (N,) uint8 (0 free, 1 fixed, 2 handle): one byte per point;
- the handle points' positions (Nh, 3), for the affine frame and the centroid pivot (the same
  arrays, in the same order, as the in-memory path, so the frame and matrix are identical);
- the *border set* S: points within distance R of a point of another label (regions vs free).

The border set is found with a coarse voxel grid of edge R/2 (voxels holding a region point
within two voxels of voxels holding a free point, and vice versa) and then exact distances
within those voxels.
The rings (the existing :func:`splatdeform.deform.deformation`, kNN graph and all) run on S alone.
This equals the in-memory rings when every point whose kNN edges can reach a ring lies well
inside S: with r = the largest k-th-neighbour distance among the points within R/2 of the
interface, the rings are at most (rings + 1) r deep, so (rings + 1) r < R/2 makes every kNN
ball that matters lie inside S. R starts from a sampled estimate and is enlarged (another pass)
until that holds. Points near the interface whose kNN reach farther than that (isolated
outliers) are reported. The geometry (voxel keys, distances, the frame from moments) is
:mod:`splatdeform.deform.border`; here: the passes over the file and the labels.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from splatdeform import deform as df
from splatdeform.basis.result import Basis
from splatdeform.deform.border import (
    Moments,
    distance_to_other,
    frame_from_moments,
    in_sorted,
    initial_radius,
    kth_distance,
    merge_keys,
    near_voxels,
    voxel_keys,
)
from splatdeform.deform.handle import AffineFrame, delta_for_transform, handle_frame
from splatdeform.deform.regions import check_region_counts, not_adjacent
from splatdeform.edit.config import EditConfig
from splatdeform.edit.selectors import Indices, Property, leaves, map_leaves, select
from splatdeform.edit.selectors.indices import index_mask
from splatdeform.edit.stream.progress import Progress
from splatdeform.errors import ProcessingError
from splatdeform.geometry import bounds
from splatdeform.io import ChunkFile
from splatdeform.model import PointModel

FREE, FIXED, HANDLE = 0, 1, 2


class ChunkModel(PointModel):
    """A chunk of a bigger model: region selectors see the whole file's bounding box."""

    lo: np.ndarray
    hi: np.ndarray

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        return self.lo, self.hi


def as_chunk(model: PointModel, lo: np.ndarray, hi: np.ndarray) -> ChunkModel:
    """``model`` (no copy) as a ChunkModel whose bbox() is (lo, hi) (3,) each."""
    chunk = ChunkModel(**{f.name: getattr(model, f.name) for f in fields(PointModel)})
    chunk.lo, chunk.hi = lo, hi
    return chunk


@dataclass
class Plan:
    """Everything the second pass needs: labels (N,) uint8, the fit, frame, delta_c (4, 3),
    matrix (4, 4); plus the border-set deformation (for the report) and pass timings."""

    n_points: int
    lo: np.ndarray
    hi: np.ndarray
    labels: np.ndarray
    frame: AffineFrame
    matrix: np.ndarray
    delta_c: np.ndarray
    border: df.Deformation
    border_points: int
    radius: float
    timings: dict[str, float] = field(default_factory=dict)
    split: object = None  # the split test's Decision (splatdeform.edit.stream.split), or None


def chunk_ranges(n: int, chunk: int):
    for start in range(0, n, chunk):
        yield start, min(start + chunk, n)


def _no_basis(points: np.ndarray, fit) -> Basis:
    k = fit.weights.shape[1]
    return Basis(values=np.zeros((points.shape[0], k)), gradients=None)


def bbox_pass(src: ChunkFile, chunk: int, quiet: bool, sample_size: int = 200_000):
    """(lo (3,), hi (3,), sample (M, 3)) with a strided sample of about sample_size points."""
    n = src.n_points
    stride = max(1, n // sample_size)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    sample = []
    progress = Progress("pass 1 (bounding box)", n, quiet=quiet)
    for a, b in chunk_ranges(n, chunk):
        pos = src.positions(a, b)
        c_lo, c_hi = bounds(pos)
        lo, hi = np.minimum(lo, c_lo), np.maximum(hi, c_hi)
        sample.append(pos[(-a) % stride::stride].copy())  # not a view: frees the chunk
        progress.update(b - a)
    seconds = progress.finish()
    return lo, hi, np.concatenate(sample), seconds


def _split_selectors(selectors):
    plain = [s for s in selectors if not isinstance(s, Indices)]
    index = [s for s in selectors if isinstance(s, Indices)]
    return plain, index


def _index_mask(selectors, n: int, base_dir: Path) -> np.ndarray | None:
    if not selectors:
        return None
    mask = np.zeros(n, dtype=bool)
    for sel in selectors:
        mask |= index_mask(sel.load(base_dir), n)
    return mask


@dataclass(frozen=True)
class _Rows:
    """A leaf standing in for an indices selector nested in all / not: its whole-file mask
    (N,) bool, sliced to the chunk's rows [start, start + chunk size)."""

    whole: np.ndarray
    start: int

    def mask(self, model: PointModel, base_dir: Path | None = None) -> np.ndarray:
        return self.whole[self.start:self.start + model.n_points]

    def in_units(self, units: str, frame) -> _Rows:
        return self


def _nested_indices(selectors, n: int, base_dir: Path) -> list:
    """``selectors`` with each indices leaf inside all / not turned into its whole-file mask
    (loaded once; a chunk model only knows its own rows)."""
    def whole(leaf):
        return _Rows(index_mask(leaf.load(base_dir), n), 0) if isinstance(leaf, Indices) \
            else leaf
    return [map_leaves(s, whole) for s in selectors]


def _at_rows(selectors, start: int) -> list:
    """``selectors`` with their index masks positioned at the chunk starting at ``start``."""
    if not any(isinstance(leaf, _Rows) for s in selectors for leaf in leaves(s)):
        return selectors
    return [map_leaves(s, lambda leaf: _Rows(leaf.whole, start) if isinstance(leaf, _Rows)
                       else leaf) for s in selectors]


def labels_pass(src: ChunkFile, cfg: EditConfig, base_dir: Path, lo: np.ndarray,
                hi: np.ndarray, chunk: int, quiet: bool, max_handle: int = 2**62):
    """(labels (N,) uint8, handle positions (Nh, 3) float64 or None when there are more
    than ``max_handle``, handle moments, seconds); region errors as the in-memory path
    raises them."""
    n = src.n_points
    fixed_plain, fixed_idx = _split_selectors([s.to_selector() for s in cfg.regions.fixed])
    handle_plain, handle_idx = _split_selectors([s.to_selector()
                                                 for s in cfg.regions.handle or []])
    fixed_imask = _index_mask(fixed_idx, n, base_dir)
    handle_imask = _index_mask(handle_idx, n, base_dir)
    fixed_plain = _nested_indices(fixed_plain, n, base_dir)
    handle_plain = _nested_indices(handle_plain, n, base_dir)
    need_model = any(isinstance(leaf, Property) for s in fixed_plain + handle_plain
                     for leaf in leaves(s))
    units = cfg.regions.units
    labels = np.zeros(n, dtype=np.uint8)
    handle_pos: list | None = []
    kept = 0
    moments = Moments((lo + hi) / 2)
    overlap = 0
    counts = np.zeros(3, dtype=np.int64)
    progress = Progress("pass 2 (regions)", n, quiet=quiet)
    for a, b in chunk_ranges(n, chunk):
        model = src.read(a, b) if need_model else PointModel(positions=src.positions(a, b))
        cm = as_chunk(model, lo, hi)
        fixed = select(cm, _at_rows(fixed_plain, a), units, base_dir)
        handle = select(cm, _at_rows(handle_plain, a), units, base_dir)
        if fixed_imask is not None:
            fixed |= fixed_imask[a:b]
        if handle_imask is not None:
            handle |= handle_imask[a:b]
        overlap += int((fixed & handle).sum())
        labels[a:b][fixed] = FIXED
        labels[a:b][handle] = HANDLE
        counts += np.bincount(labels[a:b], minlength=3)[:3]
        moments.add(cm.positions[handle])
        if handle_pos is not None:
            kept += int(handle.sum())
            handle_pos = None if kept > max_handle else handle_pos + [cm.positions[handle]]
        progress.update(b - a)
    seconds = progress.finish()
    # the in-memory check itself, from counts (labels give the handle its overlap points)
    check_region_counts(int(counts[FIXED]) + overlap, int(counts[HANDLE]), overlap,
                        int(counts[FREE]))
    return labels, (None if handle_pos is None else np.concatenate(handle_pos)), moments, \
        seconds


class HandleExtent:
    """The handle's extent along its axes (pass 2b read the file once more for it), gathered
    during pass 3's read of the positions instead of a pass of its own."""

    def __init__(self, labels: np.ndarray, centroid: np.ndarray, vt: np.ndarray) -> None:
        self.labels, self.centroid, self.vt = labels, centroid, vt
        self.extent = np.zeros(3)

    def __call__(self, a: int, b: int, positions: np.ndarray) -> None:
        pts = positions[self.labels[a:b] == HANDLE]
        if pts.size:
            self.extent = np.maximum(self.extent,
                                     np.abs((pts - self.centroid) @ self.vt.T).max(axis=0))


def gather_border(src: ChunkFile, labels: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                  radius: float, chunk: int, quiet: bool, max_points: int,
                  each: HandleExtent | None = None):
    """Two passes: voxels of edge radius/2 by label, then the points in voxels within two
    voxels of another label, and of those the points within ``radius`` of another label.
    Returns (global indices (S,) int64, positions (S, 3), labels (S,), distance to the other
    label (S,)). ``each(start, stop, positions)``: told every chunk of pass 3."""
    n = src.n_points
    edge = radius / 2.0
    dims = np.maximum(np.ceil((hi - lo) / edge).astype(np.int64), 1)
    if float(np.prod(dims.astype(np.float64))) > 2**62:
        raise ProcessingError("streaming: the border radius is too small for the bounding box")
    free_keys, region_keys = [], []
    progress = Progress("pass 3 (border voxels)", n, quiet=quiet)
    for a, b in chunk_ranges(n, chunk):
        p = src.positions(a, b)
        if each is not None:
            each(a, b, p)
        keys = voxel_keys(p, lo, edge, dims)
        lab = labels[a:b]
        free_keys = merge_keys(free_keys, np.unique(keys[lab == FREE]))
        region_keys = merge_keys(region_keys, np.unique(keys[lab != FREE]))
        progress.update(b - a)
    progress.finish()
    free_v = np.unique(np.concatenate(free_keys))
    region_v = np.unique(np.concatenate(region_keys))
    del free_keys, region_keys
    candidates = np.union1d(near_voxels(region_v, free_v, dims),
                            near_voxels(free_v, region_v, dims))
    idx, pos, lab = [], [], []
    taken = 0
    progress = Progress("pass 4 (border points)", n, quiet=quiet)
    for a, b in chunk_ranges(n, chunk):
        p = src.positions(a, b)
        keep = np.flatnonzero(in_sorted(voxel_keys(p, lo, edge, dims), candidates))
        taken += keep.size
        if taken > max_points:
            raise ProcessingError(
                f"streaming: more than {max_points:,} points lie near the region borders; "
                "the border does not fit the memory budget (raise --memory-budget)")
        idx.append(keep + a)
        pos.append(p[keep])
        lab.append(labels[a:b][keep])
        progress.update(b - a)
    progress.finish()
    idx, pos, lab = np.concatenate(idx), np.concatenate(pos), np.concatenate(lab)
    free = lab == FREE
    dist = distance_to_other(pos, free, radius)
    keep = dist < radius
    return idx[keep], pos[keep], lab[keep], dist[keep]


#: Passes 3 and 4 gather the points within this many times the first border radius, so that
#: the usual enlargement (one step of 1.5x the needed radius) filters what is in memory
#: instead of reading the file twice more.
_GATHER = 2.0


def _gather(src: ChunkFile, labels: np.ndarray, lo: np.ndarray, hi: np.ndarray, radius: float,
            diag: float, chunk: int, quiet: bool, max_points: int,
            each: HandleExtent | None = None):
    """(reach, indices, positions, labels, distances) of :func:`gather_border` at ``reach`` =
    _GATHER x ``radius`` (at most the diagonal), or at ``radius`` itself when that many points
    would not fit ``max_points``."""
    reach = min(_GATHER * radius, diag)
    if reach > radius:
        try:
            return (reach, *gather_border(src, labels, lo, hi, reach, chunk, quiet, max_points,
                                          each))
        except ProcessingError:   # ``each`` (a running maximum) may see the chunks again
            pass
    return (radius, *gather_border(src, labels, lo, hi, radius, chunk, quiet, max_points, each))


def build_plan(src: ChunkFile, cfg: EditConfig, base_dir: Path, *, chunk: int, quiet: bool,
               max_border: int, make_fit_fn, handle_matrix, max_handle: int = 2**62) -> Plan:
    """Passes 1-4, the rings on the border set and the fit. The handle frame and pivot come
    from the handle's points (as in memory, bit-identical) when at most ``max_handle``, else
    from streamed moments and one more pass for its extent."""
    timings: dict[str, float] = {}
    n = src.n_points
    lo, hi, sample, timings["bbox"] = bbox_pass(src, chunk, quiet)
    labels, handle_pos, moments, timings["regions"] = labels_pass(
        src, cfg, base_dir, lo, hi, chunk, quiet, max_handle)
    extent = None
    if handle_pos is not None:
        frame = handle_frame(handle_pos)
    else:   # the frame's checks now; its extent from pass 3 (no pass 2b of its own)
        frame_from_moments(moments, lambda c, vt: np.ones(3))
        centroid, _, vt = moments.centroid_and_axes()
        extent = HandleExtent(labels, centroid, vt)
        handle_pos = centroid[None, :]  # the centroid pivot
    whole = as_chunk(PointModel(positions=handle_pos), lo, hi)
    matrix = handle_matrix(cfg, whole, np.ones(handle_pos.shape[0], dtype=bool))
    del handle_pos, whole
    rings = cfg.boundary.continuity + 1
    k = cfg.boundary.neighbors
    radius = initial_radius(sample, n, k, rings, lo, hi)
    diag = float(np.linalg.norm(hi - lo)) or 1.0
    import time

    t0 = time.perf_counter()
    gathered = None
    for _attempt in range(6):
        if gathered is None or radius > gathered[0]:  # passes 3 and 4, once in the usual case
            gathered = _gather(src, labels, lo, hi, radius, diag, chunk, quiet, max_border,
                               extent)
            if extent is not None:   # every chunk seen once: the frame as pass 2b gave it
                frame = frame_from_moments(moments, lambda c, vt, e=extent.extent: e)
                extent = None
        within = gathered[4] < radius   # the border set of this radius, as its own passes
        gidx, pos, lab, dist = (a[within] for a in gathered[1:])
        kth = kth_distance(pos, k) if pos.shape[0] > 1 else np.zeros(pos.shape[0])
        core = dist <= radius / 2
        r_core = float(kth[core].max()) if core.any() else 0.0
        needed = 2.0 * (rings + 1) * r_core
        outliers = int(np.sum(~core & (kth >= dist - rings * r_core)))
        if needed < radius and (outliers == 0 or radius >= diag):
            break
        if radius >= diag:
            break
        radius = min(max(needed, radius) * 1.5, diag)
    del gathered
    delta_c = delta_for_transform(frame.control_points, matrix)
    if outliers:
        warnings.warn(f"{src.path}: {outliers} points near the region borders have their "
                      f"{k} nearest neighbours farther than the border band ({radius:.3g}); "
                      "their rings may differ from the in-memory path", stacklevel=2)
    fixed_s, handle_s = lab == FIXED, lab == HANDLE
    # a region with no point near the free region (a separate cluster: the labels pass counted
    # its points) has no rings; the in-memory rings say the same line
    if not fixed_s.any():
        raise not_adjacent("regions.fixed", "fixed")
    if not handle_s.any():
        raise not_adjacent("regions.handle", "handle")
    sub = PointModel(positions=pos)
    grads = frame.coordinate_gradients()
    bbox_model = PointModel(positions=np.stack([lo, hi]))
    border = df.prepare(
        sub, fixed_s, handle_s, control_points=frame.control_points,
        coordinates=frame.coordinates,
        coordinate_gradients=lambda p: np.broadcast_to(grads, (p.shape[0], 4, 3)),
        fit_fn=make_fit_fn(cfg, bbox_model), basis_fn=_no_basis,
        continuity=cfg.boundary.continuity, neighbors=k, frame=frame)
    timings["border"] = time.perf_counter() - t0 - border.timings.get("rings", 0.0) \
        - border.timings.get("fit", 0.0)
    timings["rings"] = border.timings.get("rings", 0.0)
    timings["fit"] = border.timings.get("fit", 0.0)
    border.constraint_idx = gidx[border.constraint_idx]  # global indices, for the report
    return Plan(n_points=n, lo=lo, hi=hi, labels=labels, frame=frame, matrix=matrix,
                delta_c=delta_c, border=border, border_points=int(gidx.size), radius=radius,
                timings=timings)
