"""One input check for both basis backends (numpy reference and OpenCL): same errors, same
messages, whatever backend ``auto`` picks."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..rbf.result import RbfFit


def check_points(points: np.ndarray) -> np.ndarray:
    """points (N, 3) of a real dtype with finite coordinates (returned as given)."""
    arr = np.asarray(points)
    if arr.dtype.kind not in "fiu":
        raise InputError(f"points: expected a real-valued (N, 3) array, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"points: expected shape (N, 3), got {arr.shape}")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        bad = int(np.flatnonzero(~np.isfinite(arr).all(axis=1))[0])
        raise InputError(f"points: expected finite coordinates, row {bad} is {arr[bad].tolist()}")
    return arr


def check_fit(fit: RbfFit) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(centers (n, 3), weights (4 + n, k), center (3,), scale) as float64, validated."""
    for name in ("centers", "weights", "normalization"):
        if not hasattr(fit, name):
            raise InputError(f"fit: expected an RbfFit, got {type(fit).__name__} without .{name}")
    centers = np.asarray(fit.centers, dtype=np.float64)
    weights = np.asarray(fit.weights, dtype=np.float64)
    if centers.ndim != 2 or centers.shape[1] != 3:
        raise InputError(f"fit.centers: expected shape (n, 3), got {centers.shape}")
    n = centers.shape[0]
    if weights.ndim != 2 or weights.shape[0] != 4 + n or weights.shape[1] < 1:
        raise InputError(
            f"fit.weights: expected shape ({4 + n}, k) with k >= 1 for {n} centers, "
            f"got {weights.shape}"
        )
    if not (np.isfinite(centers).all() and np.isfinite(weights).all()):
        raise InputError("fit: expected finite centers and weights, found NaN or inf")
    norm = fit.normalization
    if not (hasattr(norm, "center") and hasattr(norm, "scale")):
        raise InputError(f"fit.normalization: expected a Normalization, got {type(norm).__name__}")
    center = np.asarray(norm.center, dtype=np.float64).reshape(-1)
    scale = float(norm.scale)
    if center.shape != (3,) or not np.isfinite(center).all():
        raise InputError(f"fit.normalization.center: expected 3 finite values, got {center}")
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(f"fit.normalization.scale: expected a finite value > 0, got {scale}")
    return centers, weights, center, scale
