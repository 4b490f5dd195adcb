"""The config layer's one conversion: a validated :class:`EditConfig` becomes plain model-unit
data (masks, metaphors, transforms, delta_c, the fitter and basis settings) for
:mod:`splatdeform.deform`, which never sees the config."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splatdeform.deform.deformation import BasisFn, FitFn, basis_settings, fit_settings
from splatdeform.deform.metaphor import Metaphor
from splatdeform.edit.config import EditConfig
from splatdeform.edit.metaphors import Context, entries
from splatdeform.edit.metaphors.curve import points as _curve_points
from splatdeform.edit.metaphors.handle import entries as handle_entries
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
    """Every metaphor of the edit in model units, in column order (each handle, the curve)."""
    ctx = Context.of(cfg, model, base_dir)
    return [kind.metaphor(key, entry, ctx) for kind, key, entry in entries(cfg)]


def control_displacement(cfg: EditConfig, model: PointModel, deformation
                         ) -> tuple[np.ndarray, np.ndarray | list[np.ndarray] | None]:
    """delta_c (k, 3) for the configured pose of every metaphor and the handle matrices: one
    4x4 for the ``handle:`` form, a list (one per handle) for ``handles:``, None for a curve
    alone."""
    ctx = Context.of(cfg, model, None)
    parts, matrices = [], []
    for (kind, key, entry), group in zip(entries(cfg), deformation.groups, strict=True):
        part, matrix = kind.delta(key, entry, group, deformation, ctx)
        parts.append(part)
        if matrix is not None:
            matrices.append(matrix)
    delta = np.vstack(parts)
    if cfg.handle is not None:
        return delta, matrices[0]
    return delta, matrices or None


def handle_configs(cfg: EditConfig) -> list[tuple[str, object]]:
    """(config key, handle config) of every handle, in column order."""
    return [(key, entry[0]) for key, entry in handle_entries(cfg)]


def handle_matrix(cfg: EditConfig, model: PointModel, handle: np.ndarray) -> np.ndarray:
    """The 4x4 transform of the single ``handle:`` form."""
    return transform_matrix(cfg.handle, "handle", cfg.regions.units, model, handle)


def curve_points(cfg: EditConfig, model: PointModel) -> tuple[np.ndarray, np.ndarray, float]:
    """The curve in model units: control points (k, 3), moved_to (k, 3), capture radius."""
    return _curve_points(cfg.curve, cfg.regions.units, model)


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
    """The basis columns k an edit of handles only will have (4 per handle: the affine
    control points); None when a curve's count depends on the model."""
    from splatdeform.edit.metaphors import curve, entries

    found = entries(cfg)
    if not found or any(kind is curve for kind, _, _ in found):
        return None
    return 4 * len(found)


make_fit_fn = fit_fn  # the names the stream planner takes them by
make_basis_fn = basis_fn

__all__ = ["control_displacement", "curve_points", "fit_fn", "fixed_mask", "handle_configs",
           "handle_matrix", "metaphors", "region_mask", "transform_matrix"]
