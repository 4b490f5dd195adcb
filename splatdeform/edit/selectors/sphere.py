"""``{sphere: {center, radius}}``: the points within a ball (in relative units the centre is in
bounding-box coordinates and the radius a fraction of the bounding-box diagonal)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import Field

from splatdeform.edit import units as u
from splatdeform.edit.schema import Number, Strict, Vec3
from splatdeform.model import PointModel

NAME = "sphere"


@dataclass(frozen=True)
class Sphere:
    """Points within ``radius`` of ``center`` (inclusive), in model units.

    Parameters
    ----------
    center : tuple of 3 float
        The ball's centre (in relative units: bounding-box coordinates).
    radius : float
        Its radius (in relative units: a fraction of the bounding-box diagonal).

    Examples
    --------
    >>> import numpy as np
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)                        # a bumpy cylinder, x in [0, 4]
    >>> ball = sd.Sphere(center=(4, 0, 0), radius=0.8)
    >>> mask = ball.mask(bar)
    >>> bool(np.linalg.norm(bar.positions[mask] - [4, 0, 0], axis=1).max() <= 0.8)
    True
    >>> both = sd.select(bar, [ball, sd.Sphere(center=(0, 0, 0), radius=0.8)])
    >>> int(both.sum()) > int(mask.sum())             # a list of selectors is a union
    True
    """

    center: tuple[float, float, float]
    radius: float

    def mask(self, model: PointModel, base_dir: Path | None = None) -> np.ndarray:
        """(N,) bool."""
        center, radius = np.asarray(self.center, float), float(self.radius)
        return np.sum((model.positions - center) ** 2, axis=1) <= radius * radius

    def in_units(self, units: str, frame: u.Frame) -> Sphere:
        u.check_units(units)
        if units == "model":
            return self
        return Sphere(tuple(u.point(self.center, units, frame)),
                      u.length(self.radius, units, frame))

    def to_config(self, base_dir: Path | None = None) -> dict:
        return {NAME: {"center": [float(v) for v in self.center], "radius": float(self.radius)}}


class SphereCfg(Strict):
    center: Vec3 = Field(description="The ball's centre (in relative units bounding-box "
                         "coordinates)")
    radius: Number = Field(gt=0, description="Its radius (in relative units a fraction of the "
                           "bounding-box diagonal)")


class Entry(Strict):
    sphere: SphereCfg = Field(description="The points within a ball")

    def to_selector(self) -> Sphere:
        return Sphere(tuple(self.sphere.center), self.sphere.radius)
