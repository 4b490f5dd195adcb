"""Region bookkeeping around the fitted field: precompute once, apply many delta_c.

Every point is fixed (F), moving (the handle H, or a curve band) or free:
- F is copied unchanged (bit-exact), whatever delta_c is.
- A moving point h moves by its control coordinates: h' = h + coords(h) @ delta_c (for a handle
  that is exactly the affine map T; pass the 4x4 matrix to use T itself).
- Only free points evaluate the RBF field through the precomputed basis: p' = p + B delta_c.
Ring points of F and H are the fit's constraints; they get their prescribed values exactly
because they are F or H points.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from . import frame as ap
from .basis.result import Basis
from .errors import InputError, RegionError
from .handle import AffineFrame, apply_affine
from .metaphor import Metaphor, handle_metaphor
from .model import PointModel
from .rbf.result import RbfFit
from .regions import check_regions
from .rings import boundary_rings, region_adjacency


@dataclass(frozen=True)
class Group:
    """One metaphor inside a deformation.

    name: its config key (``regions.handle``, ``handles[1]``, ``curve``).
    columns: (start, stop): its columns of delta_c (k rows of delta_c in all).
    rows: (Nm,) int64 positions of its points in ``Deformation.moving_idx``.
    frame: a handle's affine frame (its points then get the handle's 4x4 map verbatim).
    """

    name: str
    columns: tuple[int, int]
    rows: np.ndarray
    frame: AffineFrame | None = None


@dataclass
class Deformation:
    """A precomputed deformation of one model.

    fixed / moving: (N,) bool masks. free_idx: (Nf,) int64. moving_idx: (Nh,) int64.
    moving_coords: (Nh, k) float64, a moving point's displacement is moving_coords @ delta_c.
    moving_gradients: (Nh, k, 3) float64, d coords / d x (constant rows for a handle).
    constraint_idx: (m,) int64 ring points; constraint_points: (m, 3);
    constraint_rhs: (m, k) float64 (M, 0 rows for F).
    control_points: (k, 3) float64 (C). frame: the handle's affine frame, or None (curves).
    fit: the RBF fit; basis: b and grad b for the free points (Nf rows).
    timings: seconds per stage. rings: ring sizes (fixed, moving).
    """

    n_points: int
    fixed: np.ndarray
    moving: np.ndarray
    free_idx: np.ndarray
    moving_idx: np.ndarray
    moving_coords: np.ndarray
    moving_gradients: np.ndarray
    constraint_idx: np.ndarray
    constraint_points: np.ndarray
    constraint_rhs: np.ndarray
    control_points: np.ndarray
    fit: RbfFit
    basis: Basis
    frame: AffineFrame | None = None
    timings: dict[str, float] = field(default_factory=dict)
    ring_sizes: tuple[list[int], list[int]] = ((), ())
    groups: list[Group] = field(default_factory=list)

    def handle_groups(self) -> list[Group]:
        """The groups whose points get a handle's 4x4 map verbatim (those with a frame)."""
        if not self.groups:  # one metaphor built without groups (older caches, custom code)
            rows = np.arange(self.moving_idx.size)
            return [Group("handle", (0, self.k), rows, self.frame)] if self.frame else []
        return [g for g in self.groups if g.frame is not None]

    @property
    def k(self) -> int:
        return int(self.control_points.shape[0])


BasisFn = Callable[[np.ndarray, RbfFit], Basis]
FitFn = Callable[[np.ndarray, np.ndarray], RbfFit]


def prepare(model: PointModel, fixed: np.ndarray, moving: np.ndarray, *,
            control_points: np.ndarray,
            coordinates: Callable[[np.ndarray], np.ndarray],
            coordinate_gradients: Callable[[np.ndarray], np.ndarray],
            fit_fn: FitFn, basis_fn: BasisFn, continuity: int = 2, neighbors: int = 10,
            moving_name: str = "handle", frame: AffineFrame | None = None) -> Deformation:
    """:func:`prepare_metaphors` for one metaphor given as masks and callables.

    coordinates(points (M, 3)) -> (M, k) control coordinates of moving points (called with the
    moving points in index order); coordinate_gradients(points (M, 3)) -> (M, k, 3).
    """
    if not moving.any():
        check_regions(fixed, moving, handle_name=moving_name)
    idx = np.flatnonzero(moving)
    pts = model.positions[idx]
    metaphor = Metaphor(moving_name, idx, np.asarray(control_points, dtype=np.float64),
                        coordinates(pts), coordinate_gradients(pts), frame)
    return prepare_metaphors(model, fixed, [metaphor], fit_fn=fit_fn, basis_fn=basis_fn,
                             continuity=continuity, neighbors=neighbors)


def _moving_columns(n_points: int, metaphors: list[Metaphor]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[Group]]:
    """Stack the metaphors' columns: moving_idx (Nh,), coords (Nh, k), gradients (Nh, k, 3)
    and the groups. A point's row is zero outside its own metaphor's columns."""
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


def prepare_metaphors(model: PointModel, fixed: np.ndarray, metaphors: list[Metaphor], *,
                      fit_fn: FitFn, basis_fn: BasisFn, continuity: int = 2,
                      neighbors: int = 10) -> Deformation:
    """Rings, constraints, one fit and one basis for a fixed mask (N,) bool and any number of
    metaphors (handles and curves): k = the sum of their columns.

    Raises RegionError when a metaphor is empty, overlaps the fixed region or another
    metaphor, or has no point next to the free region.
    """
    if continuity not in (0, 1, 2):
        raise RegionError.at("boundary.continuity", f"expected 0, 1 or 2, got {continuity}")
    if not metaphors:
        raise RegionError.at("regions", "an edit needs at least one handle or curve")
    n = model.n_points
    for mph in metaphors:
        _check_metaphor(fixed, mph, n)
    moving_idx, coords_all, grads_all, groups = _moving_columns(n, metaphors)
    moving = np.zeros(n, dtype=bool)
    moving[moving_idx] = True
    name = _short(metaphors[0].name) if len(metaphors) == 1 else "handle"
    check_regions(fixed, moving, handle_name=name)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    adj = region_adjacency(model, fixed, moving, neighbors, continuity + 2)
    fixed_rings, moving_rings = boundary_rings(adj, fixed, moving, continuity + 1, name)
    if len(metaphors) > 1:
        first_ring = moving_rings[0]
        for mph in metaphors:
            if not np.isin(mph.idx, first_ring, assume_unique=True).any():
                raise RegionError.at(mph.name, "no point of it is adjacent to the free "
                                     "region (is it enclosed by another region or a "
                                     "separate component? raise boundary.neighbors)")
    timings["rings"] = time.perf_counter() - t0

    fixed_c = np.concatenate(fixed_rings)
    moving_c = np.concatenate(moving_rings)
    lookup = np.full(n, -1, dtype=np.int64)
    lookup[moving_idx] = np.arange(moving_idx.size)
    constraint_idx = np.concatenate([fixed_c, moving_c])
    k = coords_all.shape[1]
    rhs = np.zeros((constraint_idx.size, k))
    rhs[fixed_c.size:] = coords_all[lookup[moving_c]]

    t0 = time.perf_counter()
    fit = fit_fn(model.positions[constraint_idx], rhs)
    timings["fit"] = time.perf_counter() - t0

    free_idx = np.flatnonzero(~(fixed | moving))
    t0 = time.perf_counter()
    basis = basis_fn(model.positions[free_idx], fit)
    timings["basis"] = time.perf_counter() - t0
    frames = [g.frame for g in groups if g.frame is not None]
    return Deformation(
        n_points=n, fixed=fixed, moving=moving, free_idx=free_idx,
        moving_idx=moving_idx, moving_coords=coords_all, moving_gradients=grads_all,
        constraint_idx=constraint_idx, constraint_points=model.positions[constraint_idx],
        constraint_rhs=rhs,
        control_points=np.vstack([mph.control_points for mph in metaphors]), fit=fit,
        basis=basis, frame=frames[0] if len(metaphors) == 1 and frames else None,
        timings=timings,
        ring_sizes=([r.size for r in fixed_rings], [r.size for r in moving_rings]),
        groups=groups,
    )


def _check_metaphor(fixed: np.ndarray, mph: Metaphor, n: int) -> None:
    """Empty or overlapping the fixed region: one line naming the metaphor's key."""
    mask = np.zeros(n, dtype=bool)
    mask[mph.idx] = True
    if mph.name.startswith("regions.") or " " in mph.name:
        check_regions(fixed, mask, handle_name=_short(mph.name))
        return
    if not mask.any():
        raise RegionError.at(f"{mph.name}", "selects no point; widen it")
    both = fixed & mask
    if both.any():
        raise RegionError.at(f"{mph.name}", f"overlaps regions.fixed in {int(both.sum())} points; "
                          "they must be disjoint")


def _short(name: str) -> str:
    """``regions.handle`` -> ``handle`` (check_regions prefixes ``regions.``)."""
    return name[len("regions."):] if name.startswith("regions.") else name


def prepare_handle(model: PointModel, fixed: np.ndarray, handle: np.ndarray, *,
                   fit_fn: FitFn, basis_fn: BasisFn, continuity: int = 2,
                   neighbors: int = 10) -> Deformation:
    """:func:`prepare_metaphors` for one handle (k = 4 affine frame coordinates)."""
    if not handle.any():
        check_regions(fixed, handle)
    return prepare_metaphors(model, fixed, [handle_metaphor(model.positions, handle)],
                             fit_fn=fit_fn, basis_fn=basis_fn, continuity=continuity,
                             neighbors=neighbors)


def prepare_handles(model: PointModel, fixed: np.ndarray, handles: list[np.ndarray], *,
                    fit_fn: FitFn, basis_fn: BasisFn, continuity: int = 2,
                    neighbors: int = 10) -> Deformation:
    """Several handles in one edit: k = 4 per handle, one fit, one basis, one apply."""
    metaphors = [handle_metaphor(model.positions, h, f"handles[{i}].region")
                 for i, h in enumerate(handles)]
    return prepare_metaphors(model, fixed, metaphors, fit_fn=fit_fn, basis_fn=basis_fn,
                             continuity=continuity, neighbors=neighbors)


def _deform_gaussians(model: PointModel, out: PointModel, idx: np.ndarray,
                      jac: np.ndarray) -> None:
    """Sigma' = J Sigma J^T for 3DGS splats ``idx`` (similarities composed directly, else J R S
    re-factored by a relatively accurate SVD) and SH bands 1..3 rotated by the polar R of J.
    Splats whose J is exactly I are left bit-identical (see :mod:`splatdeform.gaussians`)."""
    from .gaussians import deform_gaussians

    g = model.gaussians
    sh_rest = None if g.sh_rest is None else g.sh_rest[idx]
    new = deform_gaussians(g.scale_log[idx], g.rotation[idx], sh_rest, jac)
    out.gaussians.scale_log[idx] = new.scale_log
    out.gaussians.rotation[idx] = new.rotation
    if new.sh_rest is not None:
        out.gaussians.sh_rest[idx] = new.sh_rest


def _transform_attributes(model: PointModel, out: PointModel, idx: np.ndarray,
                          jac: np.ndarray) -> None:
    if model.normals is not None:
        out.normals[idx] = ap.transform_normals(jac, model.normals[idx])
    if model.axes is not None:
        out.axes[idx] = ap.transform_axes(jac, model.axes[idx])
    elif model.radius is not None and model.normals is not None:
        axes = ap.transform_axes(jac, ap.radius_to_axes(model.normals[idx], model.radius[idx]))
        out.radius[idx] = ap.axes_to_radius(axes)
    if model.gaussians is not None:
        _deform_gaussians(model, out, idx, jac)


def handle_matrices(deformation: Deformation, moving_matrix
                    ) -> list[tuple[Group, np.ndarray]]:
    """Pair the handle groups with their 4x4 maps: ``moving_matrix`` is None (every moving
    point by its coordinates), one (4, 4) matrix (exactly one handle), or a sequence with one
    matrix (or None) per handle, in the deformation's handle order."""
    if moving_matrix is None:
        return []
    groups = deformation.handle_groups()
    if isinstance(moving_matrix, np.ndarray) and moving_matrix.shape == (4, 4):
        if len(groups) != 1:
            raise InputError(f"moving_matrix: one 4x4 matrix given for {len(groups)} handles; "
                             "pass one matrix (or None) per handle")
        return [(groups[0], moving_matrix)]
    matrices = list(moving_matrix)
    if len(matrices) != len(groups):
        raise InputError(f"moving_matrix: expected {len(groups)} matrices (one per handle), "
                         f"got {len(matrices)}")
    return [(g, np.asarray(m, dtype=np.float64)) for g, m in zip(groups, matrices, strict=True)
            if m is not None]


def apply(deformation: Deformation, model: PointModel, delta_c: np.ndarray, *,
          moving_matrix=None) -> PointModel:
    """The deformed copy of ``model`` for control displacements delta_c (k, 3).

    Positions, normals (cof(J) n), tangent axes (J u), radius-only surfels (area-preserving
    radius) and 3DGS covariances follow. moving_matrix: the handles' 4x4 affine maps (one
    matrix for a single handle, or one per handle), used verbatim for handle points (else they
    move by their coordinates, m . delta_c).
    """
    if model.n_points != deformation.n_points:
        raise InputError(f"model: expected {deformation.n_points} points, got "
                         f"{model.n_points}")
    delta = np.asarray(delta_c, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        out = _apply(deformation, model, delta, moving_matrix)
    check_finite(model, out)
    return out


def _apply(deformation: Deformation, model: PointModel, delta: np.ndarray,
           moving_matrix: np.ndarray | None) -> PointModel:
    out = model.copy()
    free = deformation.free_idx
    values = deformation.basis.values.astype(np.float64, copy=False)
    out.positions[free] = ap.displace(model.positions[free], values, delta)
    mov = deformation.moving_idx
    out.positions[mov] = model.positions[mov] + deformation.moving_coords @ delta
    for group, matrix in handle_matrices(deformation, moving_matrix):
        rows = mov[group.rows]
        out.positions[rows] = apply_affine(matrix, model.positions[rows])
    needs_jac = any(a is not None for a in (model.normals, model.axes, model.gaussians))
    if needs_jac:
        if deformation.basis.gradients is None:
            raise InputError("deformation: basis has no gradients; normals/axes need them")
        grads = deformation.basis.gradients.astype(np.float64, copy=False)
        _transform_attributes(model, out, free, ap.jacobians(grads, delta))
        _transform_attributes(model, out, mov,
                              ap.jacobians(np.ascontiguousarray(deformation.moving_gradients),
                                           delta))
    return out


_F32_MAX = float(np.finfo(np.float32).max)


def _stored_limit(model: PointModel, fields: tuple[str, ...], default: float) -> float:
    """The largest magnitude the output can hold for ``fields``: a PLY source keeps each
    field's type (float32 unless it was double); new models write positions as double."""
    vertex = None if model.source is None else model.source.element("vertex")
    names = () if vertex is None else (vertex.data.dtype.names or ())
    dtypes = [vertex.data.dtype[f] for f in fields if f in names]
    if not dtypes:
        return default
    return min(float(np.finfo(d).max) if d.kind == "f" else _F32_MAX for d in dtypes)


def check_finite(model: PointModel, out: PointModel) -> None:
    """Guard after a deformation: every float it writes (positions, normals,
    axes, radii, 3DGS scales and rotations) is finite and fits the output's number type, for
    every point whose input value was finite. Raises InputError naming the attribute."""
    from .errors import InputError

    xyz = ("x", "y", "z")
    checks = [("positions", model.positions, out.positions, xyz, np.inf if model.source is None
               else _F32_MAX)]
    if out.normals is not None and model.normals is not None:
        checks.append(("normals", model.normals, out.normals, ("nx", "ny", "nz"), _F32_MAX))
    if out.axes is not None and model.axes is not None:
        checks.append(("surfel axes", model.axes, out.axes,
                       ("ux", "uy", "uz", "vx", "vy", "vz"), _F32_MAX))
    if out.radius is not None and model.radius is not None:
        checks.append(("radii", model.radius, out.radius, ("radius", "surfel_radius"),
                       _F32_MAX))
    g, g_in = out.gaussians, model.gaussians
    if g is not None and g_in is not None:
        checks.append(("gaussian scales", g_in.scale_log, g.scale_log,
                       ("scale_0", "scale_1", "scale_2"), _F32_MAX))
        checks.append(("gaussian rotations", g_in.rotation, g.rotation,
                       ("rot_0", "rot_1", "rot_2", "rot_3"), _F32_MAX))
    for what, before, after, fields, default in checks:
        limit = _stored_limit(model, fields, default)
        rows_in = np.isfinite(before).reshape(before.shape[0], -1).all(axis=1)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(after) & (np.abs(after) <= limit)
        ok = ok.reshape(after.shape[0], -1).all(axis=1)
        bad = int(np.count_nonzero(rows_in & ~ok))
        if bad:
            raise InputError(f"the deformation produced non-finite or out-of-range {what} for "
                             f"{bad:,} points; check the regions and the transform (a move "
                             "that large cannot be stored)")


def full_basis(deformation: Deformation) -> tuple[np.ndarray, np.ndarray]:
    """Basis for every point, for one-draw-call rendering: values (N, k) float32 and
    gradients (N, k, 3) float32; 0 for fixed points, control coordinates for moving points."""
    n, k = deformation.n_points, deformation.k
    values = np.zeros((n, k), dtype=np.float32)
    grads = np.zeros((n, k, 3), dtype=np.float32)
    values[deformation.free_idx] = deformation.basis.values
    if deformation.basis.gradients is not None:
        grads[deformation.free_idx] = deformation.basis.gradients
    values[deformation.moving_idx] = deformation.moving_coords
    grads[deformation.moving_idx] = deformation.moving_gradients
    return values, grads


def constraint_errors(deformation: Deformation, delta_c: np.ndarray,
                      basis_fn: BasisFn) -> tuple[float, float]:
    """Largest and RMS |d(c) - prescribed(c)| over the constraint points for this delta_c (model
    units): how well the fitted field meets the constraints it was fitted to."""
    if deformation.constraint_idx.size == 0:
        return 0.0, 0.0
    basis = basis_fn(deformation.constraint_points, deformation.fit)
    delta = np.asarray(delta_c, dtype=np.float64)
    error = (basis.values.astype(np.float64) - deformation.constraint_rhs) @ delta
    dist = np.linalg.norm(error, axis=1)
    return float(dist.max()), float(np.sqrt(np.mean(dist * dist)))


def constraint_error(deformation: Deformation, delta_c: np.ndarray,
                     basis_fn: BasisFn) -> float:
    """Largest |d(c) - prescribed(c)| over the constraint points (see constraint_errors)."""
    return constraint_errors(deformation, delta_c, basis_fn)[0]
