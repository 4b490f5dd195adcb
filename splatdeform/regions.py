"""Region selectors -> boolean masks over a model's points.

A region is the union of a list of selectors. In ``model`` units coordinates are model
coordinates. In ``relative`` units a point (or pivot/translation) u in [0, 1]^3 means
``bbox_min + u * bbox_extent``: boxes and planes are evaluated in those box coordinates, a
sphere's centre is mapped that way and its radius is a fraction of the bounding-box diagonal.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError, RegionError
from .model import PointModel


@dataclass(frozen=True)
class Box:
    """Points with min <= (x - origin) / scale <= max per axis (origin 0, scale 1: model
    coordinates; the config layer sets them for boxes written in relative units)."""

    min: tuple[float, float, float]
    max: tuple[float, float, float]
    origin: tuple[float, float, float] | None = None
    scale: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float


@dataclass(frozen=True)
class Plane:
    """Points on the side the normal points to (signed distance >= 0), in the coordinates
    (x - origin) / scale (model coordinates by default)."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    origin: tuple[float, float, float] | None = None
    scale: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Indices:
    """Explicit point indices, or a file of them (whitespace separated text, or .npy)."""

    indices: tuple[int, ...] = ()
    file: str | None = None


@dataclass(frozen=True)
class Property:
    """Points whose vertex property ``name`` equals ``equals``."""

    name: str
    equals: float


Selector = Box | Sphere | Plane | Indices | Property


def _box_frame(model: PointModel) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = model.bbox()
    extent = hi - lo
    return lo, np.where(extent > 0, extent, 1.0)


def to_model_point(model: PointModel, point, units: str) -> np.ndarray:
    """A (3,) point given in ``units`` as model coordinates (see :mod:`splatdeform.units`)."""
    from .units import Frame
    from .units import point as convert

    return convert(point, units, Frame.of(model))


def to_model_vector(model: PointModel, vector, units: str) -> np.ndarray:
    """A (3,) displacement given in ``units`` in model units (see :mod:`splatdeform.units`)."""
    from .units import Frame
    from .units import vector as convert

    return convert(vector, units, Frame.of(model))


def _in_frame(pts: np.ndarray, sel: Box | Plane) -> np.ndarray:
    if sel.origin is None:
        return pts
    return (pts - np.asarray(sel.origin, float)) / np.asarray(sel.scale, float)


def _load_indices(sel: Indices, base_dir: Path | None) -> np.ndarray:
    if sel.file is None:
        try:
            return np.asarray(sel.indices, dtype=np.int64)
        except OverflowError:
            raise InputError("indices: expected point indices below 2**63") from None
    path = Path(sel.file)
    if base_dir is not None and not path.is_absolute():
        path = base_dir / path
    if not path.is_file():
        what = "is not a regular file" if path.exists() else "indices file not found"
        raise InputError(f"{path}: {what}")
    try:
        if path.suffix == ".npy":
            raw = np.load(path, allow_pickle=False)
            if raw.dtype.kind not in "iu":
                raise ValueError(f"expected an integer array, got dtype {raw.dtype}")
            if raw.size and raw.dtype.kind == "u" and raw.max() > np.iinfo(np.int64).max:
                raise OverflowError("index too large")
            return raw.astype(np.int64).ravel()
        return np.loadtxt(path, dtype=np.int64, ndmin=1).ravel()
    except (ValueError, OverflowError) as exc:
        raise InputError(f"{path}: expected integer point indices: {exc}") from exc
    except OSError as exc:
        raise InputError(f"{path}: cannot read the indices file ({exc.strerror or exc})") from exc


def select_one(model: PointModel, sel: Selector, base_dir: Path | None = None) -> np.ndarray:
    """Mask (N,) bool of the points one model-unit selector picks."""
    pts = model.positions
    if isinstance(sel, (Box, Plane)):
        pts = _in_frame(pts, sel)
    if isinstance(sel, Box):
        lo, hi = np.asarray(sel.min, float), np.asarray(sel.max, float)
        if np.any(lo > hi):
            raise InputError(f"box: min {list(sel.min)} exceeds max {list(sel.max)}")
        return np.all((pts >= lo) & (pts <= hi), axis=1)
    if isinstance(sel, Sphere):
        center, radius = np.asarray(sel.center, float), float(sel.radius)
        return np.sum((pts - center) ** 2, axis=1) <= radius * radius
    if isinstance(sel, Plane):
        normal = np.asarray(sel.normal, float)
        if not np.linalg.norm(normal) > 0:
            raise InputError("plane: normal must be a non-zero vector")
        return (pts - np.asarray(sel.point, float)) @ normal >= 0
    if isinstance(sel, Indices):
        idx = _load_indices(sel, base_dir)
        if idx.size and (idx.min() < 0 or idx.max() >= model.n_points):
            raise InputError(f"indices: expected values in 0..{model.n_points - 1}, got "
                             f"{int(idx.min())}..{int(idx.max())}")
        mask = np.zeros(model.n_points, dtype=bool)
        mask[idx] = True
        return mask
    if isinstance(sel, Property):
        vertex = None if model.source is None else model.source.element("vertex")
        names = () if vertex is None else vertex.data.dtype.names
        if sel.name not in names:
            raise InputError(f"property: the model has no vertex property {sel.name!r} "
                             f"(it has {', '.join(names) or 'none'})")
        return vertex.data[sel.name] == sel.equals
    raise InputError(f"selector: unknown selector {sel!r}")


def select(model: PointModel, selectors: list[Selector], units: str = "model",
           base_dir: Path | None = None) -> np.ndarray:
    """Union of model-unit selectors -> mask (N,) bool.

    ``units="relative"`` is a convenience for API callers: the selectors are first converted
    by :mod:`splatdeform.units` (the config layer converts before calling, with "model").
    """
    if units != "model":
        from .units import Frame
        from .units import selectors as converted

        selectors = converted(selectors, units, Frame.of(model))
    mask = np.zeros(model.n_points, dtype=bool)
    for sel in selectors:
        mask |= select_one(model, sel, base_dir)
    return mask


def check_regions(fixed: np.ndarray, handle: np.ndarray, *, handle_name: str = "handle") -> None:
    """Raise RegionError for empty, overlapping or all-covering regions."""
    if not fixed.any():
        raise RegionError.at("regions.fixed", "selects no point; widen the fixed region")
    if not handle.any():
        raise RegionError.at(f"regions.{handle_name}",
                             f"selects no point; widen the {handle_name} region")
    both = fixed & handle
    if both.any():
        raise RegionError.at("regions", f"fixed and {handle_name} regions overlap in "
                          f"{int(both.sum())} points; they must be disjoint")
    if (fixed | handle).all():
        raise RegionError.at("regions", f"fixed and {handle_name} regions cover every point; "
                          "leave a free region between them")
