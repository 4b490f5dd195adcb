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

import importlib
from typing import TYPE_CHECKING, Any

from .errors import ConfigError, FormatError, InputError, ProcessingError, SplatdeformError

__version__ = "0.1.0"

# Public names are imported on first use so that `splatdeform info` starts without loading scipy,
# the fitter or the renderer.
_LAZY = {
    "Deformation": "deform", "apply": "deform", "full_basis": "deform",
    "compose_transform": "handle", "delta_for_transform": "handle",
    "load": "io", "save": "io", "PointModel": "model", "estimate_normals": "normals",
    "Box": "regions", "Indices": "regions", "Plane": "regions", "Property": "regions",
    "Sphere": "regions", "select": "regions",
    "prepare_handle": "api", "prepare_handles": "api", "delta_for": "api",
}

if TYPE_CHECKING:  # pragma: no cover
    from .api import delta_for, prepare_handle, prepare_handles
    from .deform import Deformation, apply, full_basis
    from .handle import compose_transform, delta_for_transform
    from .io import load, save
    from .model import PointModel
    from .normals import estimate_normals
    from .regions import Box, Indices, Plane, Property, Sphere, select


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'splatdeform' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


__all__ = [
    "Box", "ConfigError", "Deformation", "FormatError", "Indices", "InputError", "Plane",
    "PointModel", "ProcessingError", "Property", "Sphere", "SplatdeformError", "apply",
    "compose_transform", "delta_for", "delta_for_transform", "estimate_normals", "full_basis",
    "load", "prepare_handle", "prepare_handles", "save", "select",
]
