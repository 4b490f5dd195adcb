"""The metaphors an edit config can hold: a registry of kinds, each one module that turns its
config entries into model-unit :class:`~splatdeform.deform.metaphor.Metaphor` data (points,
control points, coordinates) and, for a pose, into its rows of delta_c.

A kind module has ``entries(cfg) -> [(key, entry)]``, ``metaphor(key, entry, ctx)``,
``delta(key, entry, group, deformation, ctx) -> (delta_c rows (k, 3), 4x4 matrix | None)``,
``basis_key(entry)`` (what of it determines the basis, for ``--reuse``), ``label(n)`` (what
``n`` of them are called in the counts line) and ``CAPABILITIES``
(:class:`~splatdeform.edit.metaphors.capabilities.Capabilities`: the runs it can take part in;
:func:`splatdeform.edit.capable.refusal` is the one query, e.g. whether an edit streams).
:data:`KINDS` fixes the column order (every handle, then the curve). A new metaphor is one
module plus one line in :data:`KINDS` (and its key in the edit config).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from splatdeform.edit.config import EditConfig
from splatdeform.edit.metaphors import curve, handle
from splatdeform.edit.units import Frame
from splatdeform.model import PointModel

KINDS = (handle, curve)  # one line per metaphor, in column order


@dataclass(frozen=True)
class Context:
    """What a kind needs to build model-unit data: the model, the config's folder (indices
    files), its units and the model's bounding-box frame."""

    model: PointModel
    base_dir: Path | None
    units: str
    frame: Frame

    @staticmethod
    def of(cfg: EditConfig, model: PointModel, base_dir: Path | None) -> Context:
        return Context(model, base_dir, cfg.regions.units, Frame.of(model))

    def mask(self, selector_cfgs: list) -> np.ndarray:
        """(N,) bool of a region's selector entries, put in model units here."""
        from splatdeform.edit.selectors import select

        sels = [s.to_selector().in_units(self.units, self.frame) for s in selector_cfgs]
        return select(self.model, sels, "model", self.base_dir)


def basis_keys(cfg: EditConfig) -> list:
    """(config key, what determines the basis) of every metaphor, in column order."""
    return [(key, kind.basis_key(entry)) for kind, key, entry in entries(cfg)]


def moving_label(cfg: EditConfig) -> str:
    """What the moving region is called: ``handle``, ``handles``, ``curve band``,
    ``handles + curve band``."""
    counts = [(kind, sum(1 for k, _, _ in entries(cfg) if k is kind)) for kind in KINDS]
    return " + ".join(kind.label(n) for kind, n in counts if n) or "handle"


def entries(cfg: EditConfig) -> list[tuple[Any, str, Any]]:
    """(kind module, config key, entry) of every metaphor of the edit, in column order."""
    return [(kind, key, entry) for kind in KINDS for key, entry in kind.entries(cfg)]
