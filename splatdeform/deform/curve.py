"""The curve metaphor: a B-spline curve on the surface whose control points the user moves.

- ``control_points`` (k, 3) are snapped to the nearest model point; they define a clamped
  B-spline of ``degree`` (k >= degree + 1). Parametrisation: ``chord`` (default; knots from the
  cumulative chord length of the control polygon, de Boor's averaging) or ``uniform``.
- Every model point within ``capture_radius`` of the curve joins the curve band; its control
  coordinates are the spline basis values N_i(t) at its nearest curve parameter t (they sum to 1,
  so moving every control point by v moves the band by exactly v).
- The band plays the handle's role: its rings next to the free region are constraints with right
  hand side N(t); the fixed region's rings have 0. delta_c = moved_to - control_points (k, 3), the
  user's coordinates as given (snapping only places the curve on the surface).
- Band points move by N(t(x)) delta_c; their Jacobian uses grad t = c'(t) / |c'(t)|^2 (the
  nearest-point projection, curvature ignored; 0 past the curve's ends, where t is clamped).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import BSpline
from scipy.spatial import cKDTree

from splatdeform import deform as df
from splatdeform.deform.metaphor import Metaphor
from splatdeform.errors import ConfigError, RegionError
from splatdeform.interrupts import knn_query
from splatdeform.model import PointModel

SAMPLES_PER_SPAN = 64


def knot_vector(control_points: np.ndarray, degree: int, parametrization: str) -> np.ndarray:
    """Clamped knot vector (k + degree + 1,) on [0, 1]."""
    k = control_points.shape[0]
    if parametrization == "uniform":
        inner = np.linspace(0, 1, k - degree + 1)[1:-1]
    else:
        chord = np.linalg.norm(np.diff(control_points, axis=0), axis=1)
        if not chord.sum() > 0:
            raise ConfigError.at("curve.control_points", "all control points coincide")
        params = np.concatenate([[0.0], np.cumsum(chord) / chord.sum()])
        inner = np.array([params[j:j + degree].mean() for j in range(1, k - degree)])
    return np.concatenate([np.zeros(degree + 1), inner, np.ones(degree + 1)])


class SplineCurve:
    """A clamped B-spline with identity coefficients: evaluates all k basis functions."""

    def __init__(self, control_points: np.ndarray, degree: int, parametrization: str) -> None:
        k = control_points.shape[0]
        if k < degree + 1:
            raise ConfigError.at("curve.control_points", f"a degree-{degree} curve needs at least "
                              f"{degree + 1} control points, got {k}")
        self.control_points = control_points
        self.knots = knot_vector(control_points, degree, parametrization)
        self.basis = BSpline(self.knots, np.eye(k), degree)
        self.dbasis = self.basis.derivative()

    def weights(self, t: np.ndarray) -> np.ndarray:
        """Basis values (M, k) at parameters t (M,)."""
        return self.basis(np.clip(t, 0, 1))

    def points(self, t: np.ndarray) -> np.ndarray:
        return self.weights(t) @ self.control_points

    def tangents(self, t: np.ndarray) -> np.ndarray:
        return self.dbasis(np.clip(t, 0, 1)) @ self.control_points


def capture(curve: SplineCurve, positions: np.ndarray, radius: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """Indices (M,) of points within ``radius`` of the curve and their parameters t (M,)."""
    spans = curve.control_points.shape[0] - 1
    t = np.linspace(0, 1, SAMPLES_PER_SPAN * spans + 1)
    samples = curve.points(t)
    dist, nearest = knn_query(cKDTree(samples), positions)
    idx = np.flatnonzero(dist <= radius)
    return idx, t[nearest[idx]]


def _listed(indices: np.ndarray, limit: int = 8) -> str:
    shown = ", ".join(str(int(i)) for i in indices[:limit])
    return shown + (f", ... ({indices.size} in all)" if indices.size > limit else "")


def curve_band(model: PointModel, control_points: np.ndarray, *, degree: int = 3,
               parametrization: str = "chord", capture_radius: float
               ) -> tuple[SplineCurve, np.ndarray, np.ndarray]:
    """The snapped curve, the band's point indices (M,) and their curve parameters t (M,).

    control_points: (k, 3) model units (snapped to the nearest model points);
    capture_radius: model units.
    """
    raw = np.asarray(control_points, dtype=np.float64)
    if not np.isfinite(raw).all():
        raise ConfigError.at("curve.control_points", "expected finite coordinates")
    _, snap = cKDTree(model.positions).query(raw)
    repeated = np.flatnonzero(snap[1:] == snap[:-1])
    if repeated.size:
        raise ConfigError.at("curve.control_points", f"consecutive control points snap to the same "
                          f"model point after point(s) {_listed(repeated)}; space them further "
                          "apart than the point spacing")
    control = model.positions[snap]
    curve = SplineCurve(control, degree, parametrization)
    band_idx, band_t = capture(curve, model.positions, float(capture_radius))
    if band_idx.size == 0:
        raise RegionError.at("curve.capture_radius", "captures no point of the model; raise it")
    if band_idx.size == model.n_points:
        raise RegionError.at("curve.capture_radius", "captures every point of the model; lower it")
    influence = curve.weights(band_t).max(axis=0)
    if (influence < 1e-3).any():
        lost = _listed(np.flatnonzero(influence < 1e-3))
        raise RegionError.at("curve.capture_radius",
                             f"captures {band_idx.size} points, none of them under the "
                             f"influence of control point(s) {lost}; raise it")
    return curve, band_idx, band_t


def curve_metaphor(model: PointModel, control_points: np.ndarray, *, degree: int = 3,
                   parametrization: str = "chord", capture_radius: float) -> Metaphor:
    """The curve metaphor: the capture band moves by N(t) . delta_c (k = control points);
    control points (k, 3) and capture radius in model units."""
    curve, band_idx, band_t = curve_band(model, control_points, degree=degree,
                                         parametrization=parametrization,
                                         capture_radius=capture_radius)
    order = np.argsort(band_idx)
    idx, t = band_idx[order], band_t[order]
    tangent = curve.tangents(t)
    grad_t = tangent / np.maximum(np.sum(tangent**2, axis=1, keepdims=True), 1e-300)
    grad_t[(t <= 0) | (t >= 1)] = 0.0  # beyond the ends the parameter is clamped
    grads = curve.dbasis(np.clip(t, 0, 1))[:, :, None] * grad_t[:, None, :]
    return Metaphor(name="curve band", idx=idx, control_points=curve.control_points,
                    coords=curve.weights(t), gradients=grads)


def prepare_curve(model: PointModel, fixed: np.ndarray, control_points: np.ndarray, *,
                  capture_radius: float, degree: int = 3, parametrization: str = "chord",
                  fit_fn, basis_fn, continuity: int = 2, neighbors: int = 10) -> df.Deformation:
    """Precompute a curve deformation (k = number of control points), model units."""
    mph = curve_metaphor(model, control_points, degree=degree, parametrization=parametrization,
                         capture_radius=capture_radius)
    return df.prepare_metaphors(model, fixed, [mph], fit_fn=fit_fn, basis_fn=basis_fn,
                                continuity=continuity, neighbors=neighbors)
