"""The editor's curve edit (``curve:`` of an edit YAML) as an immutable value (no web imports).

A :class:`CurveState` holds exactly what the YAML holds, in the edit's ``regions.units``:
control points (the curve is the B-spline through them, snapped to the nearest model points by
``deform``), ``moved_to`` (the pose: delta_c = moved_to - control_points), degree,
parametrization and capture radius. Keeping the YAML's own numbers means a loaded curve is saved
unchanged; the page works in model (local) coordinates through :meth:`CurveState.model_points`
and :meth:`CurveState.with_point`.

:func:`curve_view` gives what the page draws: the band mask and the snapped curve sampled with
its spline weights (the moved curve is samples + weights . delta_c).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from splatdeform.edit import units as u

from ..errors import InputError
from ..model import PointModel

DEFAULT_RADIUS = 0.03  # a new curve's capture radius: this fraction of the model's diagonal
SAMPLES = 96  # points of the drawn curve

Point = tuple[float, float, float]


@dataclass(frozen=True)
class CurveState:
    """One curve, in ``units`` as the YAML holds it (see the module docstring).

    control, moved: k points each ((3,) float tuples); capture_radius: a length in units."""

    control: tuple[Point, ...]
    moved: tuple[Point, ...]
    degree: int = 3
    parametrization: str = "chord"
    capture_radius: float = 0.05

    @staticmethod
    def from_config(c: Any) -> CurveState:
        """From a validated ``curve:`` entry (:class:`splatdeform.edit.config.CurveCfg`)."""
        return CurveState(tuple(_pt(p) for p in c.control_points),
                          tuple(_pt(p) for p in c.moved_to), int(c.degree),
                          str(c.parametrization), float(c.capture_radius))

    @staticmethod
    def new(model: PointModel, units: str, at: np.ndarray) -> CurveState:
        """A curve of one control point at ``at`` (model coordinates), capture radius
        :data:`DEFAULT_RADIUS` of the diagonal."""
        frame = u.Frame.of(model)
        p = _to_units(at, units, frame)
        radius = DEFAULT_RADIUS * (1.0 if units == "relative" else model.diagonal())
        return CurveState((p,), (p,), capture_radius=radius)

    def to_yaml(self) -> dict[str, Any]:
        return {"control_points": [list(p) for p in self.control],
                "moved_to": [list(p) for p in self.moved], "degree": self.degree,
                "parametrization": self.parametrization, "capture_radius": self.capture_radius}

    @property
    def k(self) -> int:
        return len(self.control)

    @property
    def complete(self) -> bool:
        """Enough control points for its degree."""
        return self.k >= self.degree + 1

    def basis_key(self) -> tuple:
        """What determines the fit (all but ``moved``)."""
        return (self.control, self.degree, self.parametrization, self.capture_radius)

    def model_points(self, model: PointModel, units: str) -> tuple[np.ndarray, np.ndarray, float]:
        """Control points (k, 3), moved_to (k, 3) and the capture radius in model units."""
        frame = u.Frame.of(model)
        given = np.array([u.point(p, units, frame) for p in self.control]).reshape(-1, 3)
        moved = np.array([u.point(p, units, frame) for p in self.moved]).reshape(-1, 3)
        return given, moved, u.length(self.capture_radius, units, frame)

    def with_point(self, model: PointModel, units: str, index: int, at: np.ndarray, *,
                   moved: bool) -> CurveState:
        """Control point ``index`` (``moved``: its moved_to; else the point itself, its
        moved_to following it) at ``at`` (model coordinates)."""
        self._check(index)
        p = _to_units(at, units, u.Frame.of(model))
        mv = list(self.moved)
        mv[index] = p
        if moved:
            return replace(self, moved=tuple(mv))
        ctl = list(self.control)
        ctl[index] = p
        return replace(self, control=tuple(ctl), moved=tuple(mv))

    def appended(self, model: PointModel, units: str, at: np.ndarray) -> CurveState:
        """One more control point at the end (model coordinates), not moved."""
        p = _to_units(at, units, u.Frame.of(model))
        return replace(self, control=self.control + (p,), moved=self.moved + (p,))

    def without(self, index: int) -> CurveState | None:
        """Control point ``index`` removed (None when it was the last one)."""
        self._check(index)
        if self.k == 1:
            return None
        keep = [i for i in range(self.k) if i != index]
        return replace(self, control=tuple(self.control[i] for i in keep),
                       moved=tuple(self.moved[i] for i in keep))

    def with_settings(self, model: PointModel, units: str, *, capture_radius: float | None = None,
                      degree: int | None = None, parametrization: str | None = None
                      ) -> CurveState:
        """New capture radius (model units), degree (1..5) or parametrization."""
        out = self
        if capture_radius is not None:
            r = float(capture_radius)
            if not (np.isfinite(r) and r > 0):
                raise InputError("curve.capture_radius: expected a positive number")
            frame = u.Frame.of(model)
            out = replace(out, capture_radius=r / frame.diagonal if units == "relative" else r)
        if degree is not None:
            if int(degree) not in range(1, 6):
                raise InputError(f"curve.degree: expected 1 to 5, got {degree}")
            out = replace(out, degree=int(degree))
        if parametrization is not None:
            if parametrization not in ("chord", "uniform"):
                raise InputError("curve.parametrization: expected chord or uniform, got "
                                 f"{parametrization!r}")
            out = replace(out, parametrization=parametrization)
        return out

    def reset(self) -> CurveState:
        """moved_to back on the control points (no deformation)."""
        return replace(self, moved=self.control)

    def _check(self, index: int) -> None:
        if not 0 <= index < self.k:
            raise InputError(f"curve: no control point {index} (the curve has {self.k})")


def _pt(p) -> Point:
    a = [float(v) for v in p]
    return (a[0], a[1], a[2])


def _to_units(at, units: str, frame: u.Frame) -> Point:
    a = np.asarray(at, dtype=np.float64).reshape(3)
    if not np.isfinite(a).all():
        raise InputError("curve: expected 3 finite coordinates")
    return _pt((a - frame.origin) / frame.extent if units == "relative" else a)


@dataclass(frozen=True)
class CurveView:
    """band: (N,) bool points the curve moves (all False while the curve is incomplete or
    invalid); samples: (S, 3) float64 model points along the snapped curve; weights: (S, k)
    float64 spline weights there (the moved curve is samples + weights @ delta_c);
    problem: why there is no band, or None."""

    band: np.ndarray
    samples: np.ndarray
    weights: np.ndarray
    problem: str | None


def curve_view(curve: CurveState, model: PointModel, units: str) -> CurveView:
    """The band and the drawn curve of ``curve`` (see :class:`CurveView`)."""
    from splatdeform.deform.curve import curve_band

    given, _, radius = curve.model_points(model, units)
    none = np.zeros(model.n_points, dtype=bool)
    empty = np.zeros((0, 3)), np.zeros((0, curve.k))
    if not curve.complete:
        return CurveView(none, *empty,
                         f"curve.control_points: a degree-{curve.degree} curve needs at least "
                         f"{curve.degree + 1} control points, got {curve.k}; click more on "
                         "the model")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            spline, band_idx, _ = curve_band(model, given, degree=curve.degree,
                                             parametrization=curve.parametrization,
                                             capture_radius=radius)
    except InputError as exc:
        return CurveView(none, *empty, str(exc))
    band = none.copy()
    band[band_idx] = True
    t = np.linspace(0.0, 1.0, SAMPLES)
    return CurveView(band, spline.points(t), spline.weights(t), None)
