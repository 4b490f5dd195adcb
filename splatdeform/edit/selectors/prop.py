"""``{property: {name, equals | in | min | max}}``: the points whose vertex property matches
(e.g. a LiDAR classification, an intensity range, a GPS time window); no units.

``equals: v`` and ``in: [v, ...]`` test membership; ``min``/``max`` bound the value (inclusive,
either or both); every condition given must hold."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import Field, model_validator

from splatdeform.edit.schema import Real, Strict
from splatdeform.edit.units import Frame, check_units
from splatdeform.model import PointModel, vertex_column

NAME = "property"


@dataclass(frozen=True)
class Property:
    """Points whose vertex property ``name`` equals ``equals``, is one of ``values``, and lies
    in [``min``, ``max``] (each condition only when given).

    Parameters
    ----------
    name : str
        A scalar vertex property of the file the model was loaded from (a PLY property, a LAS
        dimension such as ``classification`` or ``intensity``).
    equals : float, optional
        Keep the points whose value equals it.
    values : tuple of float, optional
        Keep the points whose value is one of these (the config's ``in:``).
    min, max : float, optional
        Inclusive bounds on the value.

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> _ = sd.save(bumpy_bar(2000), "bar.ply")
    >>> bar = sd.load("bar.ply")                     # red = 120 + 25 x along the bar
    >>> reddest = sd.Property("red", min=200).mask(bar)
    >>> bool(bar.positions[reddest, 0].min() >= 3.2)
    True
    >>> int(sd.Property("green", values=(140,)).mask(bar).sum())
    2000
    >>> sd.Property("intensity", min=1).mask(bar)
    Traceback (most recent call last):
    ...
    splatdeform.errors.InputError: ...bar.ply: property: no vertex property 'intensity' (...)
    """

    name: str
    equals: float | None = None
    values: tuple[float, ...] | None = None
    min: float | None = None
    max: float | None = None

    def mask(self, model: PointModel, base_dir: Path | None = None) -> np.ndarray:
        """(N,) bool."""
        column = vertex_column(model, self.name, NAME)
        mask = np.ones(column.shape[0], dtype=bool)
        if self.equals is not None:
            mask &= column == self.equals
        if self.values is not None:
            mask &= np.isin(column, np.asarray(self.values, dtype=np.float64))
        if self.min is not None:
            mask &= column >= self.min
        if self.max is not None:
            mask &= column <= self.max
        return mask

    def in_units(self, units: str, frame: Frame) -> Property:
        check_units(units)
        return self

    def to_config(self, base_dir: Path | None = None) -> dict:
        out: dict = {"name": self.name}
        if self.equals is not None:
            out["equals"] = float(self.equals)
        if self.values is not None:
            out["in"] = [float(v) for v in self.values]
        for key in ("min", "max"):
            if getattr(self, key) is not None:
                out[key] = float(getattr(self, key))
        return {NAME: out}


class PropertyCfg(Strict):
    name: str = Field(description="A scalar vertex property (PLY property or LAS dimension, "
                      "e.g. classification, intensity, gps_time)")
    equals: Real | None = Field(default=None, description="Keep the points with this value")
    in_: list[Real] | None = Field(default=None, alias="in", min_length=1,
                                   description="Keep the points whose value is one of these")
    min: Real | None = Field(default=None, description="Inclusive lower bound")
    max: Real | None = Field(default=None, description="Inclusive upper bound")

    @model_validator(mode="after")
    def _some_condition(self) -> PropertyCfg:
        if self.equals is None and self.in_ is None and self.min is None and self.max is None:
            raise ValueError("expected at least one of equals, in, min, max")
        if self.min is not None and self.max is not None and self.min > self.max:
            raise ValueError(f"min {self.min} exceeds max {self.max}")
        return self


class Entry(Strict):
    property: PropertyCfg = Field(description="The points whose vertex property matches "
                                  "(every condition given holds; at least one)")

    def to_selector(self) -> Property:
        p = self.property
        return Property(p.name, p.equals, None if p.in_ is None else tuple(p.in_), p.min, p.max)
