"""The rubber-sheeting example's data (``splatdeform example rubber_sheet``; issue 36's
``points:``): a 400 m x 2 km terrain strip "scanned" on a long drive whose trajectory drifted.
The scan is the true terrain under a smooth known warp (:func:`drift_warp`: a drift growing
along the strip to ~7 m plus two broad bumps of 2-3 m); twelve surveyed control points give the
pairs (where each lies in the drifted scan -> its surveyed position). Seeded: the same bytes on
every machine (``data_tools.rubber_sheet_example`` and the tests use these functions)."""

from __future__ import annotations

import numpy as np

N_POINTS = 60_000
N_PAIRS = 12


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


def truth(n: int = N_POINTS, seed: int = 0) -> np.ndarray:
    """(n, 3) the true terrain (metres): rolling hills along a 400 m x 2 km strip."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform([0, 0], [400, 2000], (n, 2))
    z = 15 * np.sin(xy[:, 0] / 90) * np.cos(xy[:, 1] / 260) + 0.02 * xy[:, 1]
    return np.column_stack([xy, z + rng.normal(0, 0.05, n)])


def drift(p: np.ndarray) -> np.ndarray:
    """The known smooth warp of the scan (:func:`drift_warp` on the strip)."""
    return drift_warp(p, (0.0, 0.0, 0.0), (400.0, 2000.0, 0.0))


def control_indices(p: np.ndarray, k: int = N_PAIRS) -> np.ndarray:
    """k well-spread control points (two rows along the strip, as a survey would place)."""
    targets = [(x, y) for y in np.linspace(60, 1940, k // 2) for x in (70, 330)]
    return np.array([int(np.argmin((p[:, 0] - x) ** 2 + (p[:, 1] - y) ** 2))
                     for x, y in targets])


def pairs_csv(true: np.ndarray, scan: np.ndarray) -> str:
    """gcp.csv: a comment, the header and one row per control point (x,y,z in the drifted scan
    -> X,Y,Z surveyed, metres, 4 decimals)."""
    idx = control_indices(true)
    lines = ["# control points: x,y,z in the drifted scan -> X,Y,Z surveyed (metres)",
             "x,y,z,X,Y,Z"]
    lines += [",".join(f"{v:.4f}" for v in (*scan[i], *true[i])) for i in idx]
    return "\n".join(lines) + "\n"
