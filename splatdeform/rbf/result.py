"""Plain data produced by the fitter."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splatdeform.geometry import bounds


@dataclass(frozen=True)
class Normalization:
    """Maps model coordinates to normalised ones: ``(x - center) / scale``.

    center: (3,) float64 bounding-box centre. scale: bounding-box diagonal (> 0).
    """

    center: np.ndarray
    scale: float

    @staticmethod
    def of(points: np.ndarray) -> Normalization:
        """Normalisation of the bounding box of ``points`` (M, 3)."""
        pts = np.asarray(points, dtype=np.float64)
        lo, hi = bounds(pts)
        scale = float(np.linalg.norm(hi - lo))
        return Normalization(center=(lo + hi) / 2.0, scale=scale if scale > 0 else 1.0)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(M, 3) model coordinates -> (M, 3) float64 normalised coordinates."""
        return (np.asarray(points, dtype=np.float64) - self.center) / self.scale


@dataclass
class RbfFit:
    """A fitted triharmonic RBF field with linear polynomial, in normalised coordinates.

    centers:   (n, 3) float64 centers s_j, normalised coordinates.
    weights:   (4 + n, k) float64 W; rows are [1, x, y, z, phi_1 .. phi_n] so that
               b(p) = [1, p, |p - s_j|^3] . W for a normalised point p.
    normalization: how model coordinates map to normalised ones.
    residuals: (n_steps, k) float64 history of ||Q2^T rhs|| per right-hand-side column, one row
               after the polynomial block and one after each added center.
    converged: True when the largest constraint error met the tolerance (False: stopped at
               max_centers above it).
    tolerance: the bound on max_ic |r_ic| the fit aimed for (units of the right-hand side).
    max_error: the achieved max_ic |r_ic|, r = rhs - A W over the constraint rows (nan: unknown).
    rms_error: the achieved RMS of r over all constraints and columns (nan: unknown).
    method: "incremental" (least squares on chosen centers), "exact" (every constraint a
               center, the dense interpolation solve) or "exact-kept" (``fit.method: auto``:
               the dense interpolation solve through the kept constraints only).
    kept:      (m,) bool, the constraints an "exact-kept" fit went through when ``auto`` added
               dropped ring points it missed to the thinned subset (None: as given).
    """

    centers: np.ndarray
    weights: np.ndarray
    normalization: Normalization
    residuals: np.ndarray
    converged: bool
    tolerance: float
    max_error: float = float("nan")
    rms_error: float = float("nan")
    method: str = "incremental"
    kept: np.ndarray | None = None

    @property
    def n_centers(self) -> int:
        return int(self.centers.shape[0])

    @property
    def k(self) -> int:
        return int(self.weights.shape[1])
