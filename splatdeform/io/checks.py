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


def infinite_opacity_ok(data: np.ndarray, bad: np.ndarray, names: list[str]) -> np.ndarray:
    """``bad`` (N,) bool of 3DGS records with a non-finite attribute among ``names``, cleared
    where the only non-finite value is an opacity logit of +inf or -inf (alpha 1 or 0: valid,
    read and kept); NaN and every other non-finite attribute stay bad. Only the flagged rows
    are rechecked."""
    if "opacity" not in names or not bad.any():
        return bad
    rows = np.flatnonzero(bad)
    part = data[rows]
    ok = ~np.isnan(part["opacity"])
    for name in names:
        if name != "opacity":
            ok &= np.isfinite(part[name])
    out = bad.copy()
    out[rows[ok]] = False
    return out
