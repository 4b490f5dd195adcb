"""Editor selectors: the config's box / sphere / plane selectors as editable shapes.

A selector lives in the edit's ``regions.units`` (``model`` or ``relative``), exactly as the YAML
holds it, so that the masks the editor shows are the masks ``splatdeform deform`` computes. The
viewer and the gizmos work in model coordinates: :func:`shape_of` gives a selector's model-space
shape and :func:`with_shape` writes a moved or resized model-space shape back in the selector's
units.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from splatdeform.edit.selectors import Box, Plane, Selector, Sphere
from splatdeform.edit.units import Frame

from ..errors import InputError
from ..model import PointModel

KINDS = ("box", "sphere", "plane")


@dataclass(frozen=True)
class Shape:
    """A selector in model coordinates.

    kind: "box" | "sphere" | "plane" | "other" (indices/property: not editable).
    center: (3,) float64 box centre, sphere centre or plane point.
    size: (3,) float64 box extent (box), (r, r, r) (sphere), zeros otherwise.
    normal: (3,) float64 unit plane normal (plane), zeros otherwise.
    """

    kind: str
    center: np.ndarray
    size: np.ndarray
    normal: np.ndarray


def _frame(model: PointModel, units: str) -> tuple[np.ndarray, np.ndarray, float]:
    """(origin (3,), per-axis scale (3,), radius scale) mapping ``units`` to model units."""
    if units == "relative":
        frame = Frame.of(model)
        return frame.origin, frame.extent, frame.diagonal
    return np.zeros(3), np.ones(3), 1.0


def _floats(v) -> list[float]:
    return [float(x) for x in np.asarray(v, dtype=np.float64).ravel()]


def shape_of(sel: Selector, model: PointModel, units: str) -> Shape:
    """The model-space shape of ``sel`` (given in ``units``)."""
    lo, ext, rscale = _frame(model, units)
    zero = np.zeros(3)
    if isinstance(sel, Box):
        bmin = lo + np.asarray(sel.min, float) * ext
        bmax = lo + np.asarray(sel.max, float) * ext
        return Shape("box", (bmin + bmax) / 2, bmax - bmin, zero)
    if isinstance(sel, Sphere):
        r = float(sel.radius) * rscale
        return Shape("sphere", lo + np.asarray(sel.center, float) * ext, np.full(3, r), zero)
    if isinstance(sel, Plane):
        n = np.asarray(sel.normal, float) / ext  # box-coordinate normal -> model normal
        length = np.linalg.norm(n)
        return Shape("plane", lo + np.asarray(sel.point, float) * ext, zero,
                     n / length if length > 0 else n)
    return Shape("other", zero, zero, zero)


def with_shape(sel: Selector, model: PointModel, units: str, *, center=None, size=None,
               normal=None) -> Selector:
    """``sel`` with a new model-space centre / size (box extent, or sphere radius as any of the
    three) / plane normal, written back in ``units``. Unchanged parts stay bit-identical."""
    lo, ext, rscale = _frame(model, units)
    shape = shape_of(sel, model, units)
    c = shape.center if center is None else np.asarray(center, float)
    if isinstance(sel, Box):
        if center is None and size is None:
            return sel
        s = shape.size if size is None else np.abs(np.asarray(size, float))
        bmin, bmax = (c - s / 2 - lo) / ext, (c + s / 2 - lo) / ext
        return Box(tuple(_floats(bmin)), tuple(_floats(bmax)))
    if isinstance(sel, Sphere):
        center_u = sel.center if center is None else tuple(_floats((c - lo) / ext))
        radius = sel.radius if size is None else float(np.max(np.abs(size))) / rscale
        return Sphere(center_u, radius)
    if isinstance(sel, Plane):
        point = sel.point if center is None else tuple(_floats((c - lo) / ext))
        nrm = sel.normal if normal is None else tuple(_floats(np.asarray(normal, float) * ext))
        return Plane(point, nrm)
    raise InputError(f"selector: {type(sel).__name__.lower()} selectors cannot be moved in the "
                     "editor; edit them in the YAML")


def default_selector(kind: str, model: PointModel, units: str, *, center=None,
                     fraction: float = 0.15) -> Selector:
    """A new box/sphere/plane at ``center`` (model coordinates; default the bbox centre), sized
    ``fraction`` of the bounding box (plane: normal +x)."""
    if kind not in KINDS:
        raise InputError(f"selector: expected one of {', '.join(KINDS)}, got {kind!r}")
    blo, bhi = model.bbox()
    c = (blo + bhi) / 2 if center is None else np.asarray(center, float)
    extent = np.maximum(bhi - blo, 1e-9 * max(model.diagonal(), 1e-300))
    seed: Selector
    if kind == "box":
        seed = Box((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        return with_shape(seed, model, units, center=c, size=extent * fraction)
    if kind == "sphere":
        seed = Sphere((0.0, 0.0, 0.0), 1.0)
        return with_shape(seed, model, units, center=c,
                          size=np.full(3, fraction * model.diagonal() / 2))
    seed = Plane((0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    return with_shape(seed, model, units, center=c, normal=(1.0, 0.0, 0.0))


def to_yaml(sel: Selector, base_dir: Path | None = None) -> dict[str, Any]:
    """The config mapping of one selector (``{box: {min, max}}`` ...); an indices file is made
    absolute against ``base_dir`` so the YAML can be written anywhere."""
    to_config = getattr(sel, "to_config", None)
    if to_config is None:
        raise InputError(f"selector: unknown selector {sel!r}")
    return to_config(base_dir)


def from_text(text: str, model: PointModel, units: str, base_dir: Path) -> Selector:
    """One selector of any kind typed in the page, as YAML or JSON (``{all: [{box: ...},
    {not: {property: {name: classification, equals: 2}}}]}``), validated like the edit config
    and evaluated once (an unknown property is its one line). In the edit's ``units``. An
    ``indices: {file: ...}`` is refused here (the page reads no file the user did not open):
    load it from an EDIT.yaml."""
    import yaml
    from pydantic import TypeAdapter, ValidationError

    from splatdeform.edit.config import validation_error
    from splatdeform.edit.selectors import SelectorCfg, leaves, select

    try:
        data = yaml.safe_load(str(text))
    except yaml.YAMLError as exc:
        problem = " ".join(str(getattr(exc, "problem", None) or exc).split())
        raise InputError(f"selector: invalid YAML: {problem}") from None
    try:
        entry = TypeAdapter(SelectorCfg).validate_python(data)
    except ValidationError as exc:
        raise validation_error("selector", exc) from None
    sel = entry.to_selector()
    if any(getattr(leaf, "file", None) is not None for leaf in leaves(sel)):
        raise InputError("selector: indices: {file: ...} is read only from a loaded EDIT.yaml; "
                         "type the indices, or select them on screen")
    select(model, [sel], units, base_dir)  # an unknown property fails here, not in a later draw
    return sel
