"""``{all: [selector, ...]}``: the points every listed selector selects (intersection); the
entries may be any selectors, ``all`` and ``not`` included (a region's list is their union)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pydantic import Field

from splatdeform.edit.schema import Strict
from splatdeform.edit.units import Frame, check_units
from splatdeform.model import PointModel

if TYPE_CHECKING:
    from splatdeform.edit.selectors import SelectorCfg

NAME = "all"


@dataclass(frozen=True)
class All:
    """Intersection of ``parts`` (a tuple of selectors)."""

    parts: tuple

    def mask(self, model: PointModel, base_dir: Path | None = None) -> np.ndarray:
        """(N,) bool."""
        mask = np.ones(model.n_points, dtype=bool)
        for part in self.parts:
            mask &= part.mask(model, base_dir)
        return mask

    def in_units(self, units: str, frame: Frame) -> All:
        check_units(units)
        return All(tuple(p.in_units(units, frame) for p in self.parts))

    def to_config(self, base_dir: Path | None = None) -> dict:
        return {NAME: [p.to_config(base_dir) for p in self.parts]}


class Entry(Strict):
    all: list[SelectorCfg] = Field(min_length=1, description="The points every selector of "
                                   "the list selects (intersection; nests)")

    def to_selector(self) -> All:
        return All(tuple(e.to_selector() for e in self.all))
