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


def check_fits(what: str, values: np.ndarray, dtype: np.dtype | str, fmt: str = "") -> None:
    """Refuse (one FormatError line; the writer's caller names the output) writing ``values``
    into a column of ``dtype`` that cannot hold them, so that what a writer writes its reader
    reads back: a finite value beyond a float type's range (it would become inf), or a value
    outside an integer type's range (it would wrap). NaN and inf are the caller's business.
    ``what``: the field's name; ``fmt``: the format, for the message."""
    dtype = np.dtype(dtype)
    values = np.asarray(values)
    if values.size == 0 or dtype.kind not in "fiu" or values.dtype.kind not in "fiu":
        return
    if dtype.kind == "f":
        if values.dtype.kind == "f" and values.dtype.itemsize <= dtype.itemsize:
            return
        top = float(np.finfo(dtype).max)
        if values.dtype.kind != "f":   # no integer type reaches a float type's range
            return
        if max(-float(np.fmin.reduce(values, axis=None)),
               float(np.fmax.reduce(values, axis=None))) <= top:
            return   # two reductions, no temporaries: the usual case
        with np.errstate(invalid="ignore"):
            big = np.abs(values.astype(np.float64, copy=False)) > top
        big &= np.isfinite(values)
        if big.any():
            first = float(values.reshape(-1)[np.flatnonzero(big.reshape(-1))[0]])
            raise FormatError(f"{what} value {first:g} does not fit {fmt + ' ' if fmt else ''}"
                              f"{dtype.name} (at most {top:.3g} in magnitude); "
                              f"{int(big.sum()):,} such value(s)")
        return
    info = np.iinfo(dtype)
    with np.errstate(invalid="ignore"):
        if float(np.fmin.reduce(values, axis=None)) >= info.min and \
                float(np.fmax.reduce(values, axis=None)) <= info.max:
            return   # NaN is skipped by fmin/fmax: the caller's business
    v = values.astype(np.float64, copy=False) if values.dtype.kind == "f" else values
    with np.errstate(invalid="ignore"):
        bad = (v < info.min) | (v > info.max)
    if bad.any():
        first = values.reshape(-1)[np.flatnonzero(bad.reshape(-1))[0]]
        raise FormatError(f"{what} value {first:g} does not fit {fmt + ' ' if fmt else ''}"
                          f"{dtype.name} ({info.min}..{info.max}); {int(bad.sum()):,} such "
                          "value(s)")
