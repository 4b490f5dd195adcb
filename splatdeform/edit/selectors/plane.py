"""``{plane: {point, normal}}``: the points on the side the normal points to (signed distance
>= 0); in relative units evaluated in bounding-box coordinates, exactly."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from pydantic import Field, field_validator

from splatdeform.edit.schema import Strict, Vec3
from splatdeform.edit.selectors.box import in_frame
from splatdeform.edit.units import Frame, check_units
from splatdeform.errors import InputError
from splatdeform.model import PointModel

NAME = "plane"


@dataclass(frozen=True)
class Plane:
    """Points with (x' - point) . normal >= 0 where x' = (x - origin) / scale (model
    coordinates by default).

    Parameters
    ----------
    point : tuple of 3 float
        A point on the plane.
    normal : tuple of 3 float
        A non-zero vector (any length) towards the side that is selected.
    origin, scale : tuple of 3 float, optional
        The frame ``point`` is in (set by ``in_units("relative", frame)``; None: model units).

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)                        # a bumpy cylinder, x in [0, 4]
    >>> above = sd.Plane(point=(0, 0, 0), normal=(0, 0, 1)).mask(bar)
    >>> bool(bar.positions[above, 2].min() >= 0), bool(bar.positions[~above, 2].max() < 0)
    (True, True)
    >>> right = sd.select(bar, [sd.Plane(point=(0.5, 0, 0), normal=(1, 0, 0))], units="relative")
    >>> bool(bar.positions[right, 0].min() >= 2)     # the half beyond the middle of the box
    True
    """

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    origin: tuple[float, float, float] | None = None
    scale: tuple[float, float, float] | None = None

    def mask(self, model: PointModel, base_dir: Path | None = None) -> np.ndarray:
        """(N,) bool."""
        normal = np.asarray(self.normal, float)
        problem = normal_problem(list(self.normal))
        if problem:
            raise InputError(f"plane: normal: {problem}")
        pts = in_frame(model.positions, self.origin, self.scale)
        return (pts - np.asarray(self.point, float)) @ normal >= 0

    def in_units(self, units: str, frame: Frame) -> Plane:
        check_units(units)
        if units == "model":
            return self
        return replace(self, origin=tuple(frame.origin), scale=tuple(frame.extent))

    def to_config(self, base_dir: Path | None = None) -> dict:
        return {NAME: {"point": [float(v) for v in self.point],
                       "normal": [float(v) for v in self.normal]}}


def normal_problem(normal: list[float]) -> str:
    """What is wrong with a plane's ``normal`` ('' when nothing): the one rule of the config
    (a ValueError there) and of a Plane built in Python (an InputError)."""
    if not np.linalg.norm(np.asarray(normal, dtype=np.float64)) > 0:
        return f"expected a non-zero vector, got {normal}"
    return ""


class PlaneCfg(Strict):
    point: Vec3 = Field(description="A point on the plane (in relative units bounding-box "
                        "coordinates)")
    normal: Vec3 = Field(description="A non-zero vector towards the selected side (signed "
                         "distance >= 0)")

    @field_validator("normal")
    @classmethod
    def _nonzero(cls, normal: list[float]) -> list[float]:
        problem = normal_problem(normal)
        if problem:
            raise ValueError(problem)
        return normal


class Entry(Strict):
    plane: PlaneCfg = Field(description="The points on one side of a plane")

    def to_selector(self) -> Plane:
        return Plane(tuple(self.plane.point), tuple(self.plane.normal))
