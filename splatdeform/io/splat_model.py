"""A PointModel from decoded splats: the last step of every splat reader (.splat, .spz, .sog,
glTF). It sits above both ``splats`` (the fields) and ``ply`` (the model builder), so neither
of those imports the other's side back."""

from __future__ import annotations

from pathlib import Path

from ..errors import FormatError
from ..model import PlySource, PointModel
from .ply import model_from_source
from .splats import SplatFields, gaussian_source


def to_model(fields: SplatFields, path: str | Path, comments: list[str], *,
             drop_nonfinite: bool = False) -> PointModel:
    """A PointModel (kind gaussians) whose PLY source is the standard 3DGS vertex element.
    ``fields`` is emptied on the way (its arrays are released once copied)."""
    if fields.count == 0:
        raise FormatError(f"{path}: the file holds no splats")
    return source_model(gaussian_source(fields, comments, release=True), path,
                        drop_nonfinite=drop_nonfinite)


def source_model(source: PlySource, path: str | Path, *,
                 drop_nonfinite: bool = False) -> PointModel:
    """The PointModel of a 3DGS source (:func:`~splatdeform.io.splats.gaussian_source` or
    :func:`~splatdeform.io.splats.table_source`)."""
    if source.element("vertex").count == 0:
        raise FormatError(f"{path}: the file holds no splats")
    return model_from_source(source, path, drop_nonfinite=drop_nonfinite)
