"""``{property: {name, equals}}``: the points whose vertex property equals a value (e.g. a LiDAR
classification); no units."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splatdeform.edit.schema import Strict
from splatdeform.edit.units import Frame, check_units
from splatdeform.errors import InputError
from splatdeform.model import PointModel

NAME = "property"


@dataclass(frozen=True)
class Property:
    """Points whose vertex property ``name`` equals ``equals``."""

    name: str
    equals: float

    def mask(self, model: PointModel, base_dir: Path | None = None) -> np.ndarray:
        """(N,) bool."""
        vertex = None if model.source is None else model.source.element("vertex")
        names = () if vertex is None else vertex.data.dtype.names
        if self.name not in names:
            raise InputError(f"property: the model has no vertex property {self.name!r} "
                             f"(it has {', '.join(names) or 'none'})")
        return vertex.data[self.name] == self.equals

    def in_units(self, units: str, frame: Frame) -> Property:
        check_units(units)
        return self

    def to_config(self, base_dir: Path | None = None) -> dict:
        return {NAME: {"name": self.name, "equals": float(self.equals)}}


class PropertyCfg(Strict):
    name: str
    equals: float


class Entry(Strict):
    property: PropertyCfg

    def to_selector(self) -> Property:
        return Property(self.property.name, self.property.equals)
