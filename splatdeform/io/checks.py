"""Checks every point reader shares."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError


def nonfinite_points(path: str | Path, positions: np.ndarray, drop_nonfinite: bool) -> np.ndarray:
    """(N,) bool mask of points with NaN/Inf coordinates in ``positions`` (N, 3); raises one
    FormatError line naming the file when there are some and ``drop_nonfinite`` is off."""
    bad = ~np.isfinite(positions).all(axis=1)
    if bad.any() and not drop_nonfinite:
        raise FormatError(f"{path}: {int(bad.sum())} point(s) with NaN/Inf coordinates (first "
                          f"at index {int(np.flatnonzero(bad)[0])}); fix the file or load "
                          "with drop_nonfinite=True (CLI: --drop-nonfinite)")
    return bad
