"""Convenience entry points of the Python API (re-exported by ``splatdeform``)."""

from __future__ import annotations

from functools import partial

import numpy as np

from . import deform
from .basis import compute_basis
from .handle import delta_for_transform
from .model import PointModel
from .rbf import Normalization, fit_incremental
from .rbf.fit import DEFAULT_MAX_CENTERS, DEFAULT_TOLERANCE


def prepare_handle(model: PointModel, fixed: np.ndarray, handle: np.ndarray, *,
                   tolerance: float = DEFAULT_TOLERANCE,
                   max_centers: int = DEFAULT_MAX_CENTERS, continuity: int = 2,
                   neighbors: int = 10, backend: str = "auto",
                   device: str | None = None) -> deform.Deformation:
    """Rings, fit and basis of a handle edit for masks ``fixed``/``handle`` (N,) bool."""
    fit_fn = partial(fit_incremental, tolerance=tolerance, max_centers=max_centers,
                     normalization=Normalization.of(model.positions))
    basis_fn = partial(compute_basis, gradients=True, backend=backend, device=device)
    return deform.prepare_handle(model, fixed, handle, fit_fn=fit_fn, basis_fn=basis_fn,
                                 continuity=continuity, neighbors=neighbors)


def delta_for(deformation: deform.Deformation, matrix: np.ndarray) -> np.ndarray:
    """delta_c (4, 3) that moves the handle frame by the 4x4 affine ``matrix``."""
    return delta_for_transform(deformation.control_points, matrix)
