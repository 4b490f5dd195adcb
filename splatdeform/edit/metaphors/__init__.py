"""The metaphors an edit config can hold: a registry of kinds, each one module that turns its
config entries into model-unit data for :mod:`splatdeform.deform` and, for a pose, into its
rows of delta_c.

A kind module has:

- ``entries(cfg) -> [(key, entry)]``: its entries of the edit, in column order;
- ``metaphor(key, entry, ctx)``: its moving region as a
  :class:`~splatdeform.deform.metaphor.Metaphor` (points, control points, coordinates), or
  None for a kind whose columns are fitted to constraints of their own (control-point pairs);
- ``delta(key, entry, group, deformation, ctx) -> (delta_c rows (k, 3), 4x4 matrix | None)``;
- ``basis_key(entry)`` (what of it determines the basis, for ``--reuse``), ``label(n)`` (what
  ``n`` of them are called in the counts line, '' when they have no moving region) and
  ``CAPABILITIES`` (:class:`~splatdeform.edit.metaphors.capabilities.Capabilities`: the runs it
  can take part in; :func:`splatdeform.edit.capable.refusal` is the one query);
- optionally the hooks of a kind with constraints of its own, asked through
  :func:`hooked`: ``prepare`` (the rings, fit and basis with its constraints:
  :func:`splatdeform.edit.plain.precompute`), ``report`` (what ``deform`` prints of them and
  ``--residuals`` writes), ``select`` (what ``select`` shows without a fit).

:data:`KINDS` fixes the column order (every handle, then the curve, then the pairs). A new
metaphor is one module plus one line in :data:`KINDS` (and its key in the edit config).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from splatdeform.edit.config import EditConfig
from splatdeform.edit.metaphors import curve, handle, points
from splatdeform.edit.units import Frame
from splatdeform.model import PointModel

KINDS = (handle, curve, points)  # one line per metaphor, in column order


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
    return " + ".join(filter(None, (kind.label(n) for kind, n in counts if n))) or "handle"


def entries(cfg: EditConfig) -> list[tuple[Any, str, Any]]:
    """(kind module, config key, entry) of every metaphor of the edit, in column order."""
    return [(kind, key, entry) for kind in KINDS for key, entry in kind.entries(cfg)]


def hooked(cfg: EditConfig, hook: str) -> list[tuple[Any, str, Any]]:
    """(kind module, config key, entry) of the edit's entries whose kind has ``hook``
    (``prepare``, ``report``, ``select``: see the module docstring)."""
    return [(kind, key, entry) for kind, key, entry in entries(cfg) if hasattr(kind, hook)]
