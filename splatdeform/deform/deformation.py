"""Precompute a deformation once (rings -> one fit -> one basis), then apply any delta_c.

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

from splatdeform.basis.oneshot import deferred_basis
from splatdeform.basis.result import Basis
from splatdeform.deform.handle import AffineFrame
from splatdeform.deform.metaphor import Metaphor, handle_metaphor
from splatdeform.deform.regions import Group, check_regions, layout
from splatdeform.deform.thin import thin_rings
from splatdeform.model import PointModel
from splatdeform.rbf.defaults import (
    DEFAULT_MAX_CENTERS,
    DEFAULT_METHOD,
    DEFAULT_THINNING,
    DEFAULT_TOLERANCE,
)
from splatdeform.rbf.result import RbfFit


@dataclass
class Deformation:
    """A precomputed deformation of one model.

    fixed / moving: (N,) bool masks. free_idx: (Nf,) int64. moving_idx: (Nh,) int64.
    moving_coords: (Nh, k) float64, a moving point's displacement is moving_coords @ delta_c.
    moving_gradients: (Nh, k, 3) float64, d coords / d x (constant rows for a handle).
    constraint_idx: (m,) int64 ring points; constraint_points: (m, 3);
    constraint_rhs: (m, k) float64 (M, 0 rows for F).
    control_points: (k, 3) float64 (C). groups: one per metaphor, in column order (each
    handle's affine frame with it).
    fit: the RBF fit; basis: b, grad b of the free points (Nf rows; a DeferredBasis: one-shot).
    timings: seconds per stage. rings: ring sizes (fixed, moving).
    kept: (m,) bool over the constraints: the thinned subset the incremental fit was given
    (None: every constraint). Dropped ring points are still fixed or moving points, so they
    get their prescribed values exactly; :func:`constraint_errors` covers all m.

    Made by :func:`prepare_handle`, :func:`prepare_handles` or :func:`prepare_metaphors`
    (and :meth:`splatdeform.field.Field.deformation`); applied by
    :func:`splatdeform.deform.apply` for any control displacement delta_c (k, 3).

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)
    >>> fixed = sd.select(bar, [sd.Box(min=(-1, -1, -1), max=(1, 1, 1))])
    >>> handle = sd.select(bar, [sd.Box(min=(3, -1, -1), max=(5, 1, 1))])
    >>> d = sd.prepare_handle(bar, fixed, handle, backend="numpy")
    >>> d.n_points, d.k, d.control_points.shape, d.frame is not None
    (2000, 4, (4, 3), True)
    >>> d.basis.values.shape == (d.free_idx.size, d.k)   # b(x) of every free point
    True
    >>> sorted(d.timings)
    ['basis', 'fit', 'rings']
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
    timings: dict[str, float] = field(default_factory=dict)
    ring_sizes: tuple[list[int], list[int]] = ((), ())
    groups: list[Group] = field(default_factory=list)
    kept: np.ndarray | None = None

    @property
    def n_kept(self) -> int:
        """Constraints the fit was given after thinning (all of them without thinning)."""
        return int(self.constraint_idx.size if self.kept is None else np.count_nonzero(self.kept))

    def handle_groups(self) -> list[Group]:
        """The groups whose points get a handle's 4x4 map verbatim (those with a frame)."""
        return [g for g in self.groups if g.frame is not None]

    @property
    def frame(self) -> AffineFrame | None:
        """The affine frame when the edit is exactly one handle, else None (derived from
        ``groups``: several handles each have their own)."""
        return self.groups[0].frame if len(self.groups) == 1 else None

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
    moving points in index order); coordinate_gradients(points (M, 3)) -> (M, k, 3)."""
    if not moving.any():
        check_regions(fixed, moving, handle_name=moving_name)
    idx = np.flatnonzero(moving)
    pts = model.positions[idx]
    metaphor = Metaphor(moving_name, idx, np.asarray(control_points, dtype=np.float64),
                        coordinates(pts), coordinate_gradients(pts), frame)
    return prepare_metaphors(model, fixed, [metaphor], fit_fn=fit_fn, basis_fn=basis_fn,
                             continuity=continuity, neighbors=neighbors)


def _default_fns(model: PointModel, fit_fn: FitFn | None, basis_fn: BasisFn | None
                 ) -> tuple[FitFn, BasisFn]:
    """The incremental fitter at the default tolerance (normalised on the model's bbox) and the
    automatic basis backend, for whichever of the two is not given."""
    if fit_fn is None:
        fit_fn = fit_settings(model)
    if basis_fn is None:
        basis_fn = basis_settings()
    return fit_fn, basis_fn


@dataclass(frozen=True)
class FitSettings:
    """The fitter of ``fit:`` as a callable ``fit(points, rhs, kept=None)``.

    method: ``auto`` (the cheaper by predicted cost, :mod:`splatdeform.rbf.auto`),
    ``incremental`` (least squares on the kept constraints) or ``exact`` (dense, through every
    constraint). thinning: ring thinning cell in ring widths (:mod:`splatdeform.deform.thin`;
    0 keeps every ring point), read by :func:`prepare_metaphors`. threads: the dense solve's
    threads (None: :func:`splatdeform.rbf.exact.dense_threads`); the incremental fit always
    uses one. normalization: model -> normalised coordinates (the model's bbox).
    """

    normalization: object
    tolerance: float = DEFAULT_TOLERANCE
    max_centers: int = DEFAULT_MAX_CENTERS
    selection: str = "greedy"
    method: str = DEFAULT_METHOD
    thinning: float = DEFAULT_THINNING
    threads: int | None = None

    def __call__(self, points: np.ndarray, rhs: np.ndarray,
                 kept: np.ndarray | None = None) -> RbfFit:
        """Fit ``rhs`` (m, k) at ``points`` (m, 3); ``kept`` (m,) bool: the thinned subset the
        incremental fit uses (the exact solve always takes every point)."""
        if self.method == "exact":
            from splatdeform.rbf.exact import fit_exact

            return fit_exact(points, rhs, normalization=self.normalization,
                             threads=self.threads)
        if self.method == "auto":
            from splatdeform.rbf.auto import fit_auto

            return fit_auto(points, rhs, kept=kept, tolerance=self.tolerance,
                            max_centers=self.max_centers, normalization=self.normalization,
                            selection=self.selection, threads=self.threads)
        from splatdeform.rbf import fit_incremental

        sub_p, sub_r = (points, rhs) if kept is None else (points[kept], rhs[kept])
        return fit_incremental(sub_p, sub_r, tolerance=self.tolerance,
                               max_centers=self.max_centers, selection=self.selection,
                               normalization=self.normalization)


def fit_settings(model: PointModel, *, tolerance: float = DEFAULT_TOLERANCE,
                 max_centers: int = DEFAULT_MAX_CENTERS, selection: str = "greedy",
                 method: str = DEFAULT_METHOD, thinning: float = DEFAULT_THINNING,
                 threads: int | None = None) -> FitSettings:
    """The fitter ``fit_fn(points, rhs, kept=None)`` for these settings, normalised on the
    model's bbox (see :class:`FitSettings`)."""
    from splatdeform.rbf import Normalization

    return FitSettings(Normalization.of(model.positions), tolerance, max_centers, selection,
                       method, thinning, threads)


def basis_settings(backend: str = "auto", device: str | None = None,
                   gradients: bool = True, stored: bool = True) -> BasisFn:
    """The basis evaluator ``basis_fn(points, fit)`` for a backend (numpy | opencl | auto).
    ``stored=False`` (an edit applied once): a :class:`~splatdeform.basis.oneshot.DeferredBasis`
    that :func:`apply` evaluates one-shot (d(x), J(x) from W delta_c, chunk by chunk), stored
    only if something reads it (the editor, ``--reuse``, rendering)."""
    from functools import partial

    from splatdeform.basis import compute_basis

    fn = compute_basis if stored else deferred_basis
    return partial(fn, gradients=gradients, backend=backend, device=device)


def prepare_metaphors(model: PointModel, fixed: np.ndarray, metaphors: list[Metaphor], *,
                      fit_fn: FitFn | None = None, basis_fn: BasisFn | None = None,
                      continuity: int = 2, neighbors: int = 10) -> Deformation:
    """Rings, constraints, one fit and one basis for a fixed mask (N,) bool and any number of
    metaphors (handles and curves): k = the sum of their columns. ``fit_fn`` / ``basis_fn``
    default to :func:`fit_settings` / :func:`basis_settings` with their defaults.

    Parameters
    ----------
    model : PointModel
        The model to edit.
    fixed : ndarray of bool, shape (N,)
        The fixed region (stays bit for bit).
    metaphors : list of Metaphor
        ``splatdeform.deform.handle_metaphor(positions, mask)`` and
        ``splatdeform.deform.curve_metaphor(model, control_points, capture_radius=)``, in
        the column order of delta_c.
    fit_fn, basis_fn, continuity, neighbors
        As for :func:`prepare_handle`.

    Returns
    -------
    Deformation
        k = the sum of the metaphors' columns; apply any delta_c (k, 3) with :func:`apply`.

    Raises
    ------
    RegionError
        A metaphor that is empty, overlaps the fixed region or another metaphor, or has no
        point next to the free region.

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)
    >>> fixed = sd.select(bar, [sd.Box(min=(-1, -1, -1), max=(1, 1, 1))])
    >>> handle = sd.select(bar, [sd.Box(min=(3, -1, -1), max=(5, 1, 1))])
    >>> d = sd.prepare_metaphors(bar, fixed, [sd.deform.handle_metaphor(bar.positions, handle)],
    ...                          basis_fn=sd.deform.basis_settings(backend="numpy"))
    >>> d.k, d.control_points.shape, len(d.groups)
    (4, (4, 3), 1)
    """
    fit_fn, basis_fn = _default_fns(model, fit_fn, basis_fn)
    t0 = time.perf_counter()
    lay = layout(model, fixed, metaphors, continuity=continuity, neighbors=neighbors)
    timings: dict[str, float] = {"rings": time.perf_counter() - t0}
    moving, moving_idx, coords_all = lay.moving, lay.moving_idx, lay.coords
    grads_all, groups = lay.gradients, lay.groups
    fixed_rings, moving_rings = lay.fixed_rings, lay.moving_rings
    n = model.n_points

    fixed_c = np.concatenate(fixed_rings)
    moving_c = np.concatenate(moving_rings)
    lookup = np.full(n, -1, dtype=np.int64)
    lookup[moving_idx] = np.arange(moving_idx.size)
    constraint_idx = np.concatenate([fixed_c, moving_c])
    k = coords_all.shape[1]
    rhs = np.zeros((constraint_idx.size, k))
    rhs[fixed_c.size:] = coords_all[lookup[moving_c]]

    thinning = fit_fn.thinning if isinstance(fit_fn, FitSettings) and \
        fit_fn.method != "exact" else 0.0
    t0 = time.perf_counter()
    kept = thin_rings(model.positions, list(fixed_rings) + list(moving_rings), neighbors,
                      thinning) if thinning > 0 else None
    timings["rings"] += time.perf_counter() - t0
    t0 = time.perf_counter()
    points = model.positions[constraint_idx]
    if isinstance(fit_fn, FitSettings):
        fit = fit_fn(points, rhs, kept)
    else:  # a plain fit_fn(points, rhs): given every constraint
        fit = fit_fn(points, rhs)
        kept = None
    if fit.method == "exact":
        kept = None  # the dense solve goes through every constraint
    elif fit.kept is not None:
        kept = fit.kept  # auto's dense solve added ring points the thinned one missed
    timings["fit"] = time.perf_counter() - t0

    free_idx = np.flatnonzero(~(fixed | moving))
    t0 = time.perf_counter()
    basis = (basis_fn(model.positions, fit, rows=free_idx) if getattr(basis_fn, "func", None)
             is deferred_basis else basis_fn(model.positions[free_idx], fit))  # no copy
    timings["basis"] = time.perf_counter() - t0
    return Deformation(
        n_points=n, fixed=fixed, moving=moving, free_idx=free_idx,
        moving_idx=moving_idx, moving_coords=coords_all, moving_gradients=grads_all,
        constraint_idx=constraint_idx, constraint_points=model.positions[constraint_idx],
        constraint_rhs=rhs,
        control_points=np.vstack([mph.control_points for mph in metaphors]), fit=fit,
        basis=basis,
        timings=timings,
        ring_sizes=([r.size for r in fixed_rings], [r.size for r in moving_rings]),
        groups=groups, kept=kept,
    )


def prepare_handle(model: PointModel, fixed: np.ndarray, handle: np.ndarray, *,
                   fit_fn: FitFn | None = None, basis_fn: BasisFn | None = None,
                   continuity: int = 2, neighbors: int = 10, **settings) -> Deformation:
    """:func:`prepare_metaphors` for one handle mask (N,) bool (k = 4 affine frame
    coordinates). ``settings``: tolerance, max_centers, method, thinning, threads, backend,
    device (when no ``fit_fn`` / ``basis_fn`` is given).

    Parameters
    ----------
    model : PointModel
        The model to edit.
    fixed, handle : ndarray of bool, shape (N,)
        The fixed region (stays bit for bit) and the handle (moves by its 4x4 map); they must
        not overlap, and the handle must touch the free region (every other point).
    fit_fn, basis_fn : callable, optional
        Your own fitter ``fit_fn(points, rhs)`` and basis ``basis_fn(points, fit)``; default:
        :func:`fit_settings` / :func:`basis_settings` with ``settings``.
    continuity : {0, 1, 2}
        C0 / C1 / C2 at the region borders: 1 / 2 / 3 rings of constraints.
    neighbors : int
        The kNN size that makes the rings of a point cloud.
    **settings
        ``tolerance``, ``max_centers``, ``method``, ``thinning``, ``threads`` (the fit, as
        the config's ``fit:``), ``backend``, ``device`` (the basis).

    Returns
    -------
    Deformation
        Rings, one fit and one basis: apply any 4x4 handle pose with :func:`apply`.

    Raises
    ------
    RegionError
        An empty or overlapping region, or a handle with no point next to the free region.

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)                        # a bumpy cylinder, x in [0, 4]
    >>> fixed = sd.select(bar, [sd.Box(min=(-1, -1, -1), max=(1, 1, 1))])
    >>> handle = sd.select(bar, [sd.Box(min=(3, -1, -1), max=(5, 1, 1))])
    >>> deformation = sd.prepare_handle(bar, fixed, handle, backend="numpy")
    >>> deformation.k, deformation.fit.converged
    (4, True)
    >>> int(deformation.free_idx.size) == bar.n_points - int(fixed.sum() + handle.sum())
    True
    """
    fit_fn, basis_fn = _settings_fns(model, fit_fn, basis_fn, settings)
    if not handle.any():
        check_regions(fixed, handle)
    return prepare_metaphors(model, fixed, [handle_metaphor(model.positions, handle)],
                             fit_fn=fit_fn, basis_fn=basis_fn, continuity=continuity,
                             neighbors=neighbors)


def prepare_handles(model: PointModel, fixed: np.ndarray, handles: list[np.ndarray], *,
                    fit_fn: FitFn | None = None, basis_fn: BasisFn | None = None,
                    continuity: int = 2, neighbors: int = 10, **settings) -> Deformation:
    """Several handle masks (N,) bool in one edit: k = 4 per handle, one fit, one basis, one
    apply. ``settings`` as for :func:`prepare_handle`.

    Parameters
    ----------
    model : PointModel
        The model to edit.
    fixed : ndarray of bool, shape (N,)
        The fixed region (stays bit for bit).
    handles : list of ndarray of bool, shape (N,)
        One mask per handle, disjoint from each other and from ``fixed``.
    fit_fn, basis_fn, continuity, neighbors, **settings
        As for :func:`prepare_handle`.

    Returns
    -------
    Deformation
        k = 4 per handle, in the order of ``handles`` (:func:`delta_for` takes one 4x4 each).

    Raises
    ------
    RegionError
        An empty or overlapping handle, or one with no point next to the free region.

    Examples
    --------
    >>> import numpy as np
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)
    >>> fixed = sd.select(bar, [sd.Box(min=(-1, -1, -1), max=(1, 1, 1))])
    >>> middle = sd.select(bar, [sd.Box(min=(1.8, -1, -1), max=(2.2, 1, 1))])
    >>> end = sd.select(bar, [sd.Box(min=(3, -1, -1), max=(5, 1, 1))])
    >>> d = sd.prepare_handles(bar, fixed, [middle, end], backend="numpy")
    >>> d.k, d.control_points.shape
    (8, (8, 3))
    >>> poses = [np.eye(4), sd.compose_transform(pivot=(4, 0, 0), translate=(0, 0.5, 0))]
    >>> bent = sd.apply(d, bar, sd.delta_for(d, poses), moving_matrix=poses)
    >>> np.allclose(bent.positions[middle], bar.positions[middle])      # held in place
    True
    >>> np.allclose(bent.positions[end], bar.positions[end] + [0, 0.5, 0])
    True
    """
    fit_fn, basis_fn = _settings_fns(model, fit_fn, basis_fn, settings)
    metaphors = [handle_metaphor(model.positions, h, f"handles[{i}].region")
                 for i, h in enumerate(handles)]
    return prepare_metaphors(model, fixed, metaphors, fit_fn=fit_fn, basis_fn=basis_fn,
                             continuity=continuity, neighbors=neighbors)


_SETTINGS = ("tolerance", "max_centers", "method", "thinning", "threads", "backend", "device")


def _settings_fns(model: PointModel, fit_fn: FitFn | None, basis_fn: BasisFn | None,
                  settings: dict) -> tuple[FitFn | None, BasisFn | None]:
    unknown = sorted(set(settings) - set(_SETTINGS))
    if unknown:
        raise TypeError(f"unexpected keyword argument {unknown[0]!r} (expected one of "
                        f"fit_fn, basis_fn, continuity, neighbors, {', '.join(_SETTINGS)})")
    fit_keys = {k: settings[k] for k in ("tolerance", "max_centers", "method", "thinning",
                                          "threads") if k in settings}
    basis_keys = {k: settings[k] for k in ("backend", "device") if k in settings}
    if fit_fn is None and fit_keys:
        fit_fn = fit_settings(model, **fit_keys)
    if basis_fn is None and basis_keys:
        basis_fn = basis_settings(**basis_keys)
    return fit_fn, basis_fn


def delta_for(deformation: Deformation, matrices) -> np.ndarray:
    """delta_c (k, 3) that moves each handle frame by its 4x4 affine map: one matrix for a
    single handle (or the same for every handle), or a list with one per handle in the
    deformation's handle order.

    Parameters
    ----------
    deformation : Deformation
        From :func:`prepare_handle` or :func:`prepare_handles`.
    matrices : ndarray of shape (4, 4), or list of them
        One affine map (e.g. :func:`compose_transform`) or one per handle.

    Returns
    -------
    ndarray of float64, shape (k, 3)
        The control displacement for :func:`apply`.

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)
    >>> fixed = sd.select(bar, [sd.Box(min=(-1, -1, -1), max=(1, 1, 1))])
    >>> handle = sd.select(bar, [sd.Box(min=(3, -1, -1), max=(5, 1, 1))])
    >>> d = sd.prepare_handle(bar, fixed, handle, backend="numpy")
    >>> up = sd.compose_transform(pivot=(4, 0, 0), translate=(0, 0.5, 0))
    >>> sd.delta_for(d, up)                          # every control point moves by 0.5 in y
    array([[0. , 0.5, 0. ],
           [0. , 0.5, 0. ],
           [0. , 0.5, 0. ],
           [0. , 0.5, 0. ]])
    """
    from splatdeform.deform.handle import delta_for_transform

    groups = deformation.handle_groups()
    if isinstance(matrices, np.ndarray) and matrices.shape == (4, 4):
        if len(groups) <= 1:
            return delta_for_transform(deformation.control_points, matrices)
        matrices = [matrices] * len(groups)
    parts = [delta_for_transform(g.frame.control_points, m)
             for g, m in zip(groups, matrices, strict=True)]
    return np.vstack(parts)


def constraint_errors(deformation: Deformation, delta_c: np.ndarray,
                      basis_fn: BasisFn) -> tuple[float, float]:
    """Largest and RMS |d(c) - prescribed(c)| over every constraint point (ring point), kept
    by the thinning or not, for this delta_c (model units): the real boundary error."""
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
