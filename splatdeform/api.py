"""Convenience entry points of the Python API (re-exported by ``splatdeform``)."""

from __future__ import annotations

from functools import partial

import numpy as np

from . import deform
from .basis import compute_basis
from .handle import delta_for_transform
from .model import PointModel
from .rbf import Normalization, fit_incremental
from .rbf.defaults import DEFAULT_MAX_CENTERS, DEFAULT_TOLERANCE


def _fns(model: PointModel, tolerance: float, max_centers: int, backend: str,
         device: str | None):
    fit_fn = partial(fit_incremental, tolerance=tolerance, max_centers=max_centers,
                     normalization=Normalization.of(model.positions))
    basis_fn = partial(compute_basis, gradients=True, backend=backend, device=device)
    return fit_fn, basis_fn


def prepare_handle(model: PointModel, fixed: np.ndarray, handle: np.ndarray, *,
                   tolerance: float = DEFAULT_TOLERANCE,
                   max_centers: int = DEFAULT_MAX_CENTERS, continuity: int = 2,
                   neighbors: int = 10, backend: str = "auto",
                   device: str | None = None) -> deform.Deformation:
    """Rings, fit and basis of a handle edit for masks ``fixed``/``handle`` (N,) bool."""
    fit_fn, basis_fn = _fns(model, tolerance, max_centers, backend, device)
    return deform.prepare_handle(model, fixed, handle, fit_fn=fit_fn, basis_fn=basis_fn,
                                 continuity=continuity, neighbors=neighbors)


def prepare_handles(model: PointModel, fixed: np.ndarray, handles: list[np.ndarray], *,
                    tolerance: float = DEFAULT_TOLERANCE,
                    max_centers: int = DEFAULT_MAX_CENTERS, continuity: int = 2,
                    neighbors: int = 10, backend: str = "auto",
                    device: str | None = None) -> deform.Deformation:
    """Several handles (masks (N,) bool each) in one edit: one fit, one basis (k = 4 each)."""
    fit_fn, basis_fn = _fns(model, tolerance, max_centers, backend, device)
    return deform.prepare_handles(model, fixed, handles, fit_fn=fit_fn, basis_fn=basis_fn,
                                  continuity=continuity, neighbors=neighbors)


def delta_for(deformation: deform.Deformation, matrices) -> np.ndarray:
    """delta_c (k, 3) that moves each handle frame by its 4x4 affine map: one matrix for a
    single handle, or one per handle (stacked in the deformation's handle order)."""
    groups = deformation.handle_groups()
    if isinstance(matrices, np.ndarray) and matrices.shape == (4, 4):
        if len(groups) <= 1:
            return delta_for_transform(deformation.control_points, matrices)
        matrices = [matrices] * len(groups)
    parts = [delta_for_transform(g.frame.control_points, m)
             for g, m in zip(groups, matrices, strict=True)]
    return np.vstack(parts)
