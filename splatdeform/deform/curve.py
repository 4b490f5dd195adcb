"""The curve metaphor: a B-spline curve on the surface whose control points the user moves.

- ``control_points`` (k, 3) are snapped to the nearest model point; they define a clamped
  B-spline of ``degree`` (k >= degree + 1). Parametrisation: ``chord`` (default; knots from the
  cumulative chord length of the control polygon, de Boor's averaging) or ``uniform``.
- Every model point within ``capture_radius`` of the curve joins the curve band; its control
  coordinates are the spline basis values N_i(t) at its nearest curve parameter t (they sum to 1,
  so moving every control point by v moves the band by exactly v). t is found by projection:
  the best of ``SAMPLES_PER_SPAN`` samples per span, then a safeguarded Newton iteration on the
  squared distance inside the bracket of its two neighbouring samples (:func:`project`), so t,
  and the band's displacement, are smooth functions of position (no staircase of samples).
- Within the curve's reach (its smallest radius of curvature) the nearest point is unique; a
  ``capture_radius`` beyond it makes t jump on the concave side whatever is chosen, so
  :func:`curve_band` warns with one line (:func:`min_curvature_radius`).
- The band plays the handle's role: its rings next to the free region are constraints with right
  hand side N(t); the fixed region's rings have 0. delta_c = moved_to - control_points (k, 3), the
  user's coordinates as given (snapping only places the curve on the surface).
- Band points move by N(t(x)) delta_c; their Jacobian uses the gradient of the nearest-point
  projection, grad t = c'(t) / (|c'(t)|^2 - (x - c(t)) . c''(t)) (:func:`parameter_gradient`;
  curvature included; 0 past the curve's ends, where t is clamped).
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.interpolate import BSpline
from scipy.spatial import cKDTree

from splatdeform import deform as df
from splatdeform.deform.metaphor import Metaphor
from splatdeform.errors import ConfigError, RegionError
from splatdeform.interrupts import knn_query
from splatdeform.model import PointModel

SAMPLES_PER_SPAN = 64
NEWTON_STEPS = 60  # safeguarded Newton/bisection steps of the projection (converges in ~5)


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
        self.ddbasis = self.basis.derivative(2) if degree >= 2 else None

    def weights(self, t: np.ndarray) -> np.ndarray:
        """Basis values (M, k) at parameters t (M,)."""
        return self.basis(np.clip(t, 0, 1))

    def points(self, t: np.ndarray) -> np.ndarray:
        return self.weights(t) @ self.control_points

    def tangents(self, t: np.ndarray) -> np.ndarray:
        """c'(t) (M, 3)."""
        return self.dbasis(np.clip(t, 0, 1)) @ self.control_points

    def second_derivatives(self, t: np.ndarray) -> np.ndarray:
        """c''(t) (M, 3) (zero for a polyline)."""
        if self.ddbasis is None:
            return np.zeros((np.size(t), 3))
        return self.ddbasis(np.clip(t, 0, 1)) @ self.control_points


def _samples(curve: SplineCurve) -> np.ndarray:
    spans = curve.control_points.shape[0] - 1
    return np.linspace(0, 1, SAMPLES_PER_SPAN * spans + 1)


def project(curve: SplineCurve, positions: np.ndarray, lo: np.ndarray, hi: np.ndarray,
            t0: np.ndarray) -> np.ndarray:
    """Curve parameters t (M,) in [lo, hi] minimising |x - c(t)|^2 for positions x (M, 3),
    from t0 (M,): Newton on g(t) = -(x - c) . c' (step -g / (|c'|^2 - (x - c) . c'')),
    bisection wherever the step leaves the bracket or the curvature term makes it uphill."""
    x = np.asarray(positions, dtype=np.float64)
    t, lo, hi = t0.astype(np.float64), lo.astype(np.float64), hi.astype(np.float64)
    active = np.arange(t.size)
    for _ in range(NEWTON_STEPS):
        if active.size == 0:
            break
        ta = t[active]
        r = x[active] - curve.points(ta)
        d1 = curve.tangents(ta)
        g = -np.einsum("ij,ij->i", r, d1)
        h = np.einsum("ij,ij->i", d1, d1) - np.einsum("ij,ij->i", r, curve.second_derivatives(ta))
        la, ha = lo[active], hi[active]
        la = np.where(g < 0, ta, la)  # the minimum lies beyond t in the direction of -g
        ha = np.where(g > 0, ta, ha)
        lo[active], hi[active] = la, ha
        step = np.where(h > 0, -g / np.where(h > 0, h, 1.0), np.nan)
        new = ta + step
        bad = ~((new > la) & (new < ha))
        new[bad] = 0.5 * (la[bad] + ha[bad])
        new[g == 0] = ta[g == 0]
        t[active] = new
        done = (np.abs(new - ta) <= 4 * np.finfo(float).eps) | (ha - la <= 4 * np.finfo(float).eps)
        active = active[~done]
    return t


def nearest_parameters(curve: SplineCurve, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Curve parameter t (M,) of the nearest curve point of each position (M, 3) and the
    distance (M,) to it: best sample, then :func:`project` within its neighbours' bracket."""
    ts = _samples(curve)
    _, nearest = knn_query(cKDTree(curve.points(ts)), positions)
    nearest = np.atleast_1d(nearest)
    lo = ts[np.maximum(nearest - 1, 0)]
    hi = ts[np.minimum(nearest + 1, ts.size - 1)]
    t = project(curve, positions, lo, hi, ts[nearest])
    dist = np.linalg.norm(np.asarray(positions, np.float64) - curve.points(t), axis=1)
    return t, dist


def capture(curve: SplineCurve, positions: np.ndarray, radius: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """Indices (M,) of points within ``radius`` of the curve and their parameters t (M,)."""
    ts = _samples(curve)
    samples = curve.points(ts)
    gap = np.linalg.norm(np.diff(samples, axis=0), axis=1).max()
    # candidates: a sample within radius + the largest sample gap (covers every point in range)
    dist, _ = knn_query(cKDTree(samples), positions, distance_upper_bound=radius + gap)
    cand = np.flatnonzero(np.isfinite(dist))
    t, d = nearest_parameters(curve, positions[cand])
    keep = d <= radius
    return cand[keep], t[keep]


def parameter_gradient(curve: SplineCurve, positions: np.ndarray, t: np.ndarray) -> np.ndarray:
    """grad t (M, 3) of the nearest-point parameter at positions (M, 3) with parameters t (M,):
    c' / (|c'|^2 - (x - c) . c''), from differentiating (x - c(t)) . c'(t) = 0; 0 at the clamped
    ends (t <= 0 or t >= 1) and where the denominator is not positive (beyond the reach)."""
    d1 = curve.tangents(t)
    r = np.asarray(positions, np.float64) - curve.points(t)
    h = np.einsum("ij,ij->i", d1, d1) - np.einsum("ij,ij->i", r, curve.second_derivatives(t))
    grad = d1 / np.where(h > 0, h, np.inf)[:, None]
    grad[(t <= 0) | (t >= 1)] = 0.0  # beyond the ends the parameter is clamped
    return grad


def min_curvature_radius(curve: SplineCurve) -> float:
    """The curve's smallest radius of curvature |c'|^3 / |c' x c''| over a dense sampling
    (inf for a straight curve): the reach within which the nearest point is unique."""
    ts = np.linspace(0, 1, 8 * SAMPLES_PER_SPAN * (curve.control_points.shape[0] - 1) + 1)
    d1, d2 = curve.tangents(ts), curve.second_derivatives(ts)
    bend = np.linalg.norm(np.cross(d1, d2), axis=1)
    speed = np.linalg.norm(d1, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.where(bend > 0, speed**3 / bend, np.inf)
    return float(np.nanmin(radius)) if radius.size else float("inf")


def _listed(indices: np.ndarray, limit: int = 8) -> str:
    shown = ", ".join(str(int(i)) for i in indices[:limit])
    return shown + (f", ... ({indices.size} in all)" if indices.size > limit else "")


MIN_SEPARATION = 1e-9  # control points closer than this fraction of the model's diagonal


def check_curve_points(control_points: np.ndarray, moved_to: np.ndarray, diagonal: float,
                       key: str = "curve") -> None:
    """Refuse a degenerate curve pose: ConfigError naming ``key.control_points`` or
    ``key.moved_to`` for a non-finite point, or two points (of either list) closer than
    :data:`MIN_SEPARATION` of the model's ``diagonal`` (coincident control points make the
    spline's spans vanish; coincident moved points collapse the band between them). Both
    (k, 3) in model units."""
    limit = MIN_SEPARATION * float(diagonal)
    for name, points in (("control_points", control_points), ("moved_to", moved_to)):
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
        if bad.size:
            raise ConfigError.at(f"{key}.{name}", f"point {int(bad[0])} is not finite in model "
                                 f"units ({pts[bad[0]].tolist()}); expected finite coordinates")
        with np.errstate(over="ignore", invalid="ignore"):
            gaps = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
        gaps[np.tril_indices(len(pts))] = np.inf
        if gaps.size and gaps.min() < limit:
            i, j = np.unravel_index(int(np.argmin(gaps)), gaps.shape)
            what = ("the spline would have an empty span" if name == "control_points"
                    else "the band between them would collapse")
            raise ConfigError.at(f"{key}.{name}", f"points {i} and {j} are {gaps[i, j]:.3g} "
                                 f"apart, closer than {MIN_SEPARATION:g} of the model's "
                                 f"diagonal ({limit:.3g}): {what}; expected distinct points")


def snapped_curve(model: PointModel, control_points: np.ndarray, *, degree: int = 3,
                  parametrization: str = "chord") -> SplineCurve:
    """The curve through ``control_points`` (k, 3) snapped to the nearest model points."""
    raw = np.asarray(control_points, dtype=np.float64)
    if not np.isfinite(raw).all():
        raise ConfigError.at("curve.control_points", "expected finite coordinates")
    _, snap = cKDTree(model.positions).query(raw)
    repeated = np.flatnonzero(snap[1:] == snap[:-1])
    if repeated.size:
        raise ConfigError.at("curve.control_points", f"consecutive control points snap to the same "
                          f"model point after point(s) {_listed(repeated)}; space them further "
                          "apart than the point spacing")
    return SplineCurve(model.positions[snap], degree, parametrization)


def curve_band(model: PointModel, control_points: np.ndarray, *, degree: int = 3,
               parametrization: str = "chord", capture_radius: float
               ) -> tuple[SplineCurve, np.ndarray, np.ndarray]:
    """The snapped curve, the band's point indices (M,) and their curve parameters t (M,).

    control_points: (k, 3) model units (snapped to the nearest model points);
    capture_radius: model units.
    """
    curve = snapped_curve(model, control_points, degree=degree, parametrization=parametrization)
    reach = min_curvature_radius(curve)
    if float(capture_radius) > reach:
        warnings.warn(f"curve.capture_radius {float(capture_radius):.4g} exceeds the curve's "
                      f"smallest radius of curvature {reach:.4g}: on its concave side the "
                      "nearest curve point jumps and the band tears; lower it or smooth the "
                      "curve", stacklevel=2)
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
    grad_t = parameter_gradient(curve, model.positions[idx], t)
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
