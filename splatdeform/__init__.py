"""splatdeform: real-time shape editing of scanned point models with triharmonic RBFs
(Botsch & Kobbelt, "Real-Time Shape Editing using Radial Basis Functions", EG 2005).

Python API in a few lines::

    import splatdeform as sd
    model = sd.load("bunny.ply")
    fixed = sd.select(model, [sd.Box(min=(-1, -1, -1), max=(1, 0.1, 1))])
    handle = sd.select(model, [sd.Sphere(center=(-0.02, 0.17, 0.0), radius=0.03)])
    deformation = sd.prepare_handle(model, fixed, handle, tolerance=1e-4)
    matrix = sd.compose_transform(pivot=model.positions[handle].mean(0), axis=(0, 0, 1),
                                  degrees=30, translate=(0, 0.01, 0))
    bent = sd.apply(deformation, model, sd.delta_for(deformation, matrix),
                    moving_matrix=matrix)
    sd.save(bent, "bunny_bent.ply")
"""

from __future__ import annotations

from functools import partial

import numpy as np

from .deform import Deformation, apply, full_basis
from .errors import ConfigError, FormatError, InputError, ProcessingError, SplatdeformError
from .handle import compose_transform, delta_for_transform
from .io import load, save
from .model import PointModel
from .normals import estimate_normals
from .regions import Box, Indices, Plane, Property, Sphere, select

__version__ = "0.1.0"


def prepare_handle(model: PointModel, fixed: np.ndarray, handle: np.ndarray, *,
                   tolerance: float = 1e-4, max_centers: int = 2000, continuity: int = 2,
                   neighbors: int = 10, backend: str = "auto",
                   device: str | None = None) -> Deformation:
    """Fit and precompute a handle deformation for masks ``fixed``/``handle`` (N,) bool."""
    from . import deform
    from .basis import compute_basis
    from .rbf import Normalization, fit_incremental

    fit_fn = partial(fit_incremental, tolerance=tolerance, max_centers=max_centers,
                     normalization=Normalization.of(model.positions))
    basis_fn = partial(compute_basis, gradients=True, backend=backend, device=device)
    return deform.prepare_handle(model, fixed, handle, fit_fn=fit_fn, basis_fn=basis_fn,
                                 continuity=continuity, neighbors=neighbors)


def delta_for(deformation: Deformation, matrix: np.ndarray) -> np.ndarray:
    """delta_c (4, 3) that moves the handle frame by the 4x4 affine ``matrix``."""
    return delta_for_transform(deformation.control_points, matrix)


__all__ = [
    "Box", "ConfigError", "Deformation", "FormatError", "Indices", "InputError", "Plane",
    "PointModel", "ProcessingError", "Property", "Sphere", "SplatdeformError", "apply",
    "compose_transform", "delta_for", "estimate_normals", "full_basis", "load",
    "prepare_handle", "save", "select",
]
