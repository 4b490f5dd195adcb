"""The one place ``regions.units: relative`` becomes model units (the config layer's converter).

In relative units a point u in [0, 1]^3 means ``lo + u * extent`` of the model's bounding box, a
translation is scaled by the extent per axis, and a radius (sphere, curve capture) is a fraction
of the bounding-box diagonal. Boxes and planes given in relative units stay exact: they become
model-unit selectors that carry their frame (origin ``lo``, per-axis ``scale`` = extent), so the
points are tested in box coordinates exactly as written (a box reaching 1 holds the extreme
point). Below the config layer nothing knows about units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splatdeform.errors import InputError
from splatdeform.model import PointModel

UNITS = ("model", "relative")


@dataclass(frozen=True)
class Frame:
    """A model's bounding-box frame: origin (3,) = bbox min, extent (3,) (0 extents read as 1),
    diagonal (the bbox diagonal)."""

    origin: np.ndarray
    extent: np.ndarray
    diagonal: float

    @staticmethod
    def of(model: PointModel) -> Frame:
        lo, hi = model.bbox()
        extent = hi - lo
        return Frame(lo, np.where(extent > 0, extent, 1.0), float(np.linalg.norm(extent)))


def check_units(units: str) -> None:
    if units not in UNITS:
        raise InputError(f"units: expected 'model' or 'relative', got {units!r}")


def point(p, units: str, frame: Frame) -> np.ndarray:
    """A (3,) point given in ``units`` as model coordinates."""
    check_units(units)
    v = np.asarray(p, dtype=np.float64)
    return frame.origin + v * frame.extent if units == "relative" else v


def vector(v, units: str, frame: Frame) -> np.ndarray:
    """A (3,) displacement given in ``units`` as a model-unit displacement."""
    check_units(units)
    d = np.asarray(v, dtype=np.float64)
    return d * frame.extent if units == "relative" else d


def length(r: float, units: str, frame: Frame) -> float:
    """A radius given in ``units`` (a fraction of the diagonal when relative)."""
    check_units(units)
    return float(r) * (frame.diagonal if units == "relative" else 1.0)


def selector(sel, units: str, frame: Frame):
    """``sel`` (any registered selector) as a model-unit selector: each selector module
    says what its coordinates mean (:mod:`splatdeform.edit.selectors`)."""
    return sel.in_units(units, frame)


def selectors(sels: list, units: str, frame: Frame) -> list:
    return [selector(s, units, frame) for s in sels]
