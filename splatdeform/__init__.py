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

from typing import TYPE_CHECKING

from .errors import ConfigError, FormatError, InputError, ProcessingError, SplatdeformError
from .lazy import lazy_exports

__version__ = "0.1.0"

# Public names are imported on first use so that `splatdeform info` starts without loading scipy,
# the fitter or the renderer.
_LAZY = {
    "Deformation": "deform", "apply": "deform", "full_basis": "deform",
    "compose_transform": "deform", "delta_for_transform": "deform",
    "prepare_handle": "deform", "prepare_handles": "deform", "delta_for": "deform",
    "prepare_metaphors": "deform", "estimate_normals": "deform",
    "load": "io", "save": "io", "PointModel": "model",
    "Box": "edit.selectors", "Indices": "edit.selectors", "Plane": "edit.selectors",
    "Property": "edit.selectors", "Sphere": "edit.selectors", "select": "edit.selectors",
    "run_edit": "edit", "load_edit": "edit", "Field": "field", "convert": "conversion",
}

if TYPE_CHECKING:  # pragma: no cover
    from .conversion import convert
    from .deform import (
        Deformation,
        apply,
        compose_transform,
        delta_for,
        delta_for_transform,
        estimate_normals,
        full_basis,
        prepare_handle,
        prepare_handles,
        prepare_metaphors,
    )
    from .edit import load_edit, run_edit
    from .edit.selectors import Box, Indices, Plane, Property, Sphere, select
    from .field import Field
    from .io import load, save
    from .model import PointModel


__getattr__ = lazy_exports(__name__, _LAZY)


__all__ = [
    "Box", "ConfigError", "Deformation", "Field", "FormatError", "Indices", "InputError", "Plane",
    "PointModel", "ProcessingError", "Property", "Sphere", "SplatdeformError", "apply",
    "compose_transform", "convert", "delta_for", "delta_for_transform", "estimate_normals",
    "full_basis",
    "load", "load_edit", "prepare_handle", "prepare_handles", "prepare_metaphors", "run_edit",
    "save", "select",
]
