"""``{not: selector}``: the points a selector does not select (complement within the model);
with ``all`` it subtracts (``{all: [box, {not: ground}]}``: the box minus the ground)."""

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

NAME = "not"


@dataclass(frozen=True)
class Not:
    """Complement of ``part`` (a selector)."""

    part: object

    def mask(self, model: PointModel, base_dir: Path | None = None) -> np.ndarray:
        """(N,) bool."""
        return ~self.part.mask(model, base_dir)

    def in_units(self, units: str, frame: Frame) -> Not:
        check_units(units)
        return Not(self.part.in_units(units, frame))

    def to_config(self, base_dir: Path | None = None) -> dict:
        return {NAME: self.part.to_config(base_dir)}


class Entry(Strict):
    not_: SelectorCfg = Field(alias="not", description="The points one selector does not "
                              "select (complement; nests)")

    def to_selector(self) -> Not:
        return Not(self.not_.to_selector())
