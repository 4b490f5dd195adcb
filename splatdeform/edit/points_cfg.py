"""``points:`` config models (control-point pairs; :mod:`splatdeform.deform.points`)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from splatdeform.edit.schema import MAX_VALUE, Number, Strict

_Strict = Strict

PairRow = Annotated[list[Number], Field(min_length=6, max_length=6)]


class PairsFileCfg(_Strict):
    file: str


class PointsCfg(_Strict):
    """``points:`` control-point pairs (splatdeform.deform.points): ``pairs`` a list of
    [x, y, z, X, Y, Z] or {file: CSV/TXT with a header}; ``columns``: the header's names of
    x, y, z, X, Y, Z; ``smoothing`` with scipy RBFInterpolator's meaning (data units);
    ``tolerance``: largest pair residual / largest pair displacement; ``check_pairs``: held
    out, only reported."""

    pairs: PairsFileCfg | list[PairRow]
    columns: Annotated[list[str], Field(min_length=6, max_length=6)] | None = None
    smoothing: float = Field(default=0.0, ge=0, le=MAX_VALUE)
    tolerance: float = Field(default=1e-6, gt=0, lt=1)
    check_pairs: PairsFileCfg | list[PairRow] | None = None
