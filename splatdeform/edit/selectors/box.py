"""``{box: {min, max}}``: the points inside an axis-aligned box (in relative units the box is in
bounding-box coordinates and stays exact: the selector carries its frame)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from pydantic import Field, model_validator

from splatdeform.edit.schema import Strict, Vec3
from splatdeform.edit.units import Frame, check_units
from splatdeform.errors import InputError
from splatdeform.model import PointModel

NAME = "box"


@dataclass(frozen=True)
class Box:
    """Points with min <= (x - origin) / scale <= max per axis (origin 0, scale 1: model
    coordinates; :meth:`in_units` sets them for a box written in relative units).

    Parameters
    ----------
    min, max : tuple of 3 float
        The box's corners (inclusive), in model units (or bounding-box coordinates in [0, 1]
        once ``in_units("relative", frame)`` set ``origin`` and ``scale``).
    origin, scale : tuple of 3 float, optional
        The frame the corners are in: x' = (x - origin) / scale (None: model coordinates).

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)                        # a bumpy cylinder, x in [0, 4]
    >>> mask = sd.Box(min=(-1, -1, -1), max=(1, 1, 1)).mask(bar)
    >>> mask.shape, bool(bar.positions[mask, 0].max() <= 1)
    ((2000,), True)
    >>> end = sd.select(bar, [sd.Box(min=(0.75, 0, 0), max=(1, 1, 1))], units="relative")
    >>> bool(bar.positions[end, 0].min() >= 3)      # the last quarter of the length
    True
    >>> sd.Box(min=(0, 0, 0), max=(1, 1, 1)).to_config()
    {'box': {'min': [0.0, 0.0, 0.0], 'max': [1.0, 1.0, 1.0]}}
    """

    min: tuple[float, float, float]
    max: tuple[float, float, float]
    origin: tuple[float, float, float] | None = None
    scale: tuple[float, float, float] | None = None

    def mask(self, model: PointModel, base_dir: Path | None = None) -> np.ndarray:
        """(N,) bool."""
        lo, hi = np.asarray(self.min, float), np.asarray(self.max, float)
        problem = box_problem(list(self.min), list(self.max))
        if problem:
            raise InputError(f"box: {problem}")
        return _inside(model.positions, self.origin, self.scale, lo, hi)

    def in_units(self, units: str, frame: Frame) -> Box:
        check_units(units)
        if units == "model":
            return self
        return replace(self, origin=tuple(frame.origin), scale=tuple(frame.extent))

    def to_config(self, base_dir: Path | None = None) -> dict:
        return {NAME: {"min": [float(v) for v in self.min], "max": [float(v) for v in self.max]}}


def _inside(points: np.ndarray, origin, scale, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) bool: lo <= (x - origin) / scale <= hi on every axis, one column at a time in one
    float64 buffer (the same numbers as :func:`in_frame`, without its (N, 3) temporaries and
    the 3-wide row reduction: 270k points 10 ms -> 2 ms)."""
    pts = np.asarray(points)
    out = np.ones(pts.shape[0], dtype=bool)
    col = np.empty(pts.shape[0], dtype=np.result_type(pts.dtype, np.float64))
    for a in range(3):
        col[:] = pts[:, a]
        if origin is not None:
            col -= float(origin[a])
            col /= float(scale[a])
        out &= col >= lo[a]
        out &= col <= hi[a]
    return out


def in_frame(points: np.ndarray, origin, scale) -> np.ndarray:
    """(N, 3) points in the coordinates (x - origin) / scale (unchanged without a frame)."""
    if origin is None:
        return points
    return (points - np.asarray(origin, float)) / np.asarray(scale, float)


def box_problem(lo: list[float], hi: list[float]) -> str:
    """What is wrong with corners ``lo``, ``hi`` ('' when nothing): the one rule of the config
    (a ValueError there) and of a Box built in Python (an InputError)."""
    if any(not a <= b for a, b in zip(lo, hi, strict=True)):
        return f"min {lo} exceeds max {hi}; expected min <= max on every axis"
    return ""


class BoxCfg(Strict):
    min: Vec3 = Field(description="The low corner [x, y, z] (inclusive; in relative units "
                      "bounding-box coordinates)")
    max: Vec3 = Field(description="The high corner [x, y, z] (inclusive), at least `min` on "
                      "every axis")

    @model_validator(mode="after")
    def _ordered(self) -> BoxCfg:
        problem = box_problem(self.min, self.max)
        if problem:
            raise ValueError(problem)
        return self


class Entry(Strict):
    box: BoxCfg = Field(description="The points inside an axis-aligned box")

    def to_selector(self) -> Box:
        return Box(tuple(self.box.min), tuple(self.box.max))
