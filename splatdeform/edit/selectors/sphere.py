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
    center: Vec3
    radius: Number = Field(gt=0)


class Entry(Strict):
    sphere: SphereCfg

    def to_selector(self) -> Sphere:
        return Sphere(tuple(self.sphere.center), self.sphere.radius)
