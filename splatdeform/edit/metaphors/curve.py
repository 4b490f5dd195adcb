"""The curve: ``curve:`` control points (a B-spline through them, snapped to the model), a
capture band that moves with it, and ``moved_to`` as the pose. One column per control point."""

from __future__ import annotations

from typing import Any

import numpy as np

from splatdeform.deform.metaphor import Metaphor
from splatdeform.edit import units as u
from splatdeform.edit.config import CurveCfg, EditConfig
from splatdeform.edit.metaphors.capabilities import Capabilities
from splatdeform.errors import ConfigError
from splatdeform.model import PointModel

CAPABILITIES = Capabilities(streams=0, why={"streams": "curve: curve edits do not stream yet"})


def entries(cfg: EditConfig) -> list[tuple[str, CurveCfg]]:
    return [("curve", cfg.curve)] if cfg.curve is not None else []


def basis_key(entry: CurveCfg) -> dict:
    """What of a curve determines the basis (``--reuse``): all but ``moved_to``."""
    return entry.model_dump(exclude={"moved_to"})


def label(n: int) -> str:
    return "curve band" if n == 1 else "curve bands"


def metaphor(key: str, entry: CurveCfg, ctx: Any) -> Metaphor:
    from splatdeform.deform.curve import curve_metaphor

    given, _, radius = points(entry, ctx.units, ctx.model)
    return curve_metaphor(ctx.model, given, degree=entry.degree,
                          parametrization=entry.parametrization, capture_radius=radius)


def delta(key: str, entry: CurveCfg, group: Any, deformation: Any, ctx: Any
          ) -> tuple[np.ndarray, None]:
    """moved_to - control_points: the user's points as given (not snapped)."""
    given, moved, _ = points(entry, ctx.units, ctx.model)
    return moved - given, None


def points(c: CurveCfg, units: str, model: PointModel) -> tuple[np.ndarray, np.ndarray, float]:
    """The curve in model units: control points (k, 3), moved_to (k, 3), capture radius."""
    frame = u.Frame.of(model)
    given = np.array([u.point(p, units, frame) for p in c.control_points])
    moved = np.array([u.point(p, units, frame) for p in c.moved_to])
    if moved.shape != given.shape:
        raise ConfigError.at("curve.moved_to", f"expected {given.shape[0]} points, got "
                                               f"{moved.shape[0]}")
    from splatdeform.deform.curve import check_curve_points

    check_curve_points(given, moved, frame.diagonal, "curve")
    return given, moved, u.length(c.capture_radius, units, frame)
