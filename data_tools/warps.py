"""The known smooth warp of a drifted scan (rubber-sheeting tests, benchmark and example): a
drift growing along y plus two broad bumps (metres), laid out on a bounding box."""

from __future__ import annotations

import numpy as np


def drift_warp(p: np.ndarray, lo=None, hi=None) -> np.ndarray:
    """``p`` (N, 3) float64 moved by the warp on the box ``lo``..``hi`` (default: ``p``'s own):
    x drifts by 4 t + 3 t^2 and z by 2 t, t = 0..1 along y; bumps of +3 m and -2.5 m (sigma
    150 m) at (0.3, 0.4) and (0.7, 0.7) of the box. Returns a new (N, 3) array."""
    lo = p.min(axis=0) if lo is None else np.asarray(lo, dtype=np.float64)
    hi = p.max(axis=0) if hi is None else np.asarray(hi, dtype=np.float64)
    t = (p[:, 1] - lo[1]) / (hi[1] - lo[1])
    out = p.copy()
    out[:, 0] += 4.0 * t + 3.0 * t * t
    out[:, 2] += 2.0 * t
    for c, amp in (((0.3, 0.4), 3.0), ((0.7, 0.7), -2.5)):
        cx, cy = lo[0] + c[0] * (hi[0] - lo[0]), lo[1] + c[1] * (hi[1] - lo[1])
        out[:, 2] += amp * np.exp(-((p[:, 0] - cx) ** 2 + (p[:, 1] - cy) ** 2) / (2 * 150.0**2))
    return out
