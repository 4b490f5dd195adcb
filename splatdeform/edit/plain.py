"""The config layer's one conversion: a validated :class:`EditConfig` becomes plain model-unit
data (masks, metaphors, transforms, delta_c, the fitter and basis settings) for
:mod:`splatdeform.deform`, which never sees the config."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splatdeform.deform.deformation import BasisFn, FitFn, basis_settings, fit_settings
from splatdeform.deform.metaphor import Metaphor
from splatdeform.edit.config import EditConfig
from splatdeform.edit.metaphors import Context, entries, handle, hooked
from splatdeform.edit.metaphors.handle import transform_matrix
from splatdeform.model import PointModel


def region_mask(cfg: EditConfig, selector_cfgs: list, model: PointModel,
                base_dir: Path | None) -> np.ndarray:
    """Mask (N,) bool of a region's selector entries, converted to model units here."""
    return Context.of(cfg, model, base_dir).mask(selector_cfgs)


def fixed_mask(cfg: EditConfig, model: PointModel, base_dir: Path | None) -> np.ndarray:
    """Mask (N,) bool of ``regions.fixed``."""
    return region_mask(cfg, cfg.regions.fixed, model, base_dir)


def metaphors(cfg: EditConfig, model: PointModel, base_dir: Path | None) -> list[Metaphor]:
    """Every moving-region metaphor of the edit in model units, in column order (each handle,
    the curve; control-point pairs have none)."""
    ctx = Context.of(cfg, model, base_dir)
    found = (kind.metaphor(key, entry, ctx) for kind, key, entry in entries(cfg))
    return [m for m in found if m is not None]


def precompute(cfg: EditConfig, model: PointModel, base_dir: Path | None, *,
               stored: bool = True):
    """Regions, rings, one fit and one basis for every metaphor of the edit (``stored=False``:
    the basis deferred, for one-shot evaluation by apply). A kind with constraints of its own
    (``prepare``: control-point pairs) fits them with the regions; else
    :func:`splatdeform.deform.prepare_metaphors`."""
    fixed, found = fixed_mask(cfg, model, base_dir), metaphors(cfg, model, base_dir)
    fit, basis = fit_fn(cfg, model), basis_fn(cfg, stored=stored)
    for kind, _key, _entry in hooked(cfg, "prepare"):
        return kind.prepare(cfg, model, base_dir, fixed, found, fit_fn=fit, basis_fn=basis)
    from splatdeform.deform.deformation import prepare_metaphors

    return prepare_metaphors(model, fixed, found, fit_fn=fit, basis_fn=basis,
                             continuity=cfg.boundary.continuity,
                             neighbors=cfg.boundary.neighbors)


def control_displacement(cfg: EditConfig, model: PointModel, deformation
                         ) -> tuple[np.ndarray, np.ndarray | list[np.ndarray] | None]:
    """delta_c (k, 3) for the configured pose of every metaphor (each kind's rows, in column
    order) and the handle matrices: one 4x4 for the ``handle:`` form, a list (one per handle)
    for ``handles:``, None without handles."""
    ctx = Context.of(cfg, model, None)
    parts, matrices = [], []
    for (kind, key, entry), group in zip(entries(cfg), deformation.groups, strict=True):
        part, matrix = kind.delta(key, entry, group, deformation, ctx)
        parts.append(part)
        if matrix is not None:
            matrices.append(matrix)
    return np.vstack(parts), handle.as_applied(cfg, matrices)


def report(cfg: EditConfig, model: PointModel, base_dir: Path | None, deformation,
           delta_c: np.ndarray):
    """What a kind with constraints of its own reports after the fit (the pairs' residuals,
    which ``deform`` prints and ``--residuals`` writes), None when no kind does."""
    for kind, _key, _entry in hooked(cfg, "report"):
        return kind.report(cfg, model, base_dir, deformation, delta_c)
    return None


def handle_matrix(cfg: EditConfig, model: PointModel, points: np.ndarray) -> np.ndarray:
    """The 4x4 transform of the single ``handle:`` form (``points`` (N,) bool or (M,) int64:
    its points, for a centroid pivot)."""
    return handle.single_matrix(cfg, model, points)


def fit_fn(cfg: EditConfig, model: PointModel) -> FitFn:
    """The fitter of ``fit:`` normalised on the model's bbox."""
    f = cfg.fit
    return fit_settings(model, tolerance=f.tolerance, max_centers=f.max_centers,
                        selection=f.selection, method=f.method, thinning=f.thinning,
                        threads=f.threads)


def basis_fn(cfg: EditConfig, stored: bool = True) -> BasisFn:
    """The basis of ``backend`` / ``device`` (with gradients); ``stored=False``: deferred, for
    one-shot evaluation by apply (:mod:`splatdeform.basis.oneshot`)."""
    return basis_settings(cfg.backend, cfg.device, stored=stored)


def basis_columns(cfg: EditConfig) -> int | None:
    """The basis columns k the edit will have (4 per handle: the affine control points; 3 for
    control-point pairs); None when a kind's count depends on the model (a curve)."""
    found = entries(cfg)
    counts = [kind.columns(entry) for kind, _, entry in found]
    if not found or any(c is None for c in counts):
        return None
    return sum(counts)


make_fit_fn = fit_fn  # the names the stream planner takes them by
make_basis_fn = basis_fn

__all__ = ["control_displacement", "fit_fn", "fixed_mask", "handle_matrix", "metaphors",
           "precompute", "region_mask", "report", "transform_matrix"]
