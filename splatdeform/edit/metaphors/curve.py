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

#: ``select -o`` colours (uint8 RGB): the curve snapped to the model, after the edit, its
#: control points
CURVE_BEFORE_COLOR = (200, 20, 20)
CURVE_AFTER_COLOR = (20, 160, 40)
CONTROL_POINT_COLOR = (20, 20, 20)

CAPABILITIES = Capabilities(streams=0, why={"streams": "curve: curve edits do not stream yet"})


def entries(cfg: EditConfig) -> list[tuple[str, CurveCfg]]:
    return [("curve", cfg.curve)] if cfg.curve is not None else []


def basis_key(entry: CurveCfg) -> dict:
    """What of a curve determines the basis (``--reuse``): all but ``moved_to``."""
    return entry.model_dump(exclude={"moved_to"})


def label(n: int) -> str:
    return "curve band" if n == 1 else "curve bands"


def columns(entry: CurveCfg) -> None:
    """A curve's basis columns depend on the model (its snapped control points)."""
    return None


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


def overlays(key: str, entry: CurveCfg, model: PointModel, units: str) -> tuple[list, str]:
    """What ``select -o`` draws over a curve edit's preview (the capture band is the coloured
    moving region): the curve snapped to the model (red), the curve after the edit (green: the
    same knots with each control point moved by moved_to - control_points) and the snapped
    control points (black dots); and the legend to append."""
    from splatdeform.deform.curve import SAMPLES_PER_SPAN, snapped_curve
    from splatdeform.render.overlay import Overlay

    given, moved, _ = points(entry, units, model)
    curve = snapped_curve(model, given, degree=entry.degree,
                          parametrization=entry.parametrization)
    t = np.linspace(0, 1, SAMPLES_PER_SPAN * (given.shape[0] - 1) + 1)
    before = curve.points(t)
    after = before + curve.weights(t) @ (moved - given)
    return [Overlay(before, "line", CURVE_BEFORE_COLOR, 3),
            Overlay(after, "line", CURVE_AFTER_COLOR, 3),
            Overlay(curve.control_points, "markers", CONTROL_POINT_COLOR, 4)], \
        "; curve red, moved green"
