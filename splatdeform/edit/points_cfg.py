"""``points:`` config models (control-point pairs; :mod:`splatdeform.deform.points`)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, field_validator

from splatdeform.edit.schema import MAX_VALUE, Number, Strict

_Strict = Strict

PairRow = Annotated[list[Number], Field(min_length=6, max_length=6)]


class PairsFileCfg(_Strict):
    file: str = Field(description="A CSV/TXT file of pairs (comma, semicolon, tab or blank "
                      "separated, a header line, # comments), relative to the config file")


class PointsCfg(_Strict):
    """``points:`` control-point pairs (splatdeform.deform.points): ``pairs`` a list of
    [x, y, z, X, Y, Z] or {file: CSV/TXT with a header}; ``columns``: the header's names of
    x, y, z, X, Y, Z; ``smoothing`` with scipy RBFInterpolator's meaning (data units);
    ``tolerance``: largest pair residual / largest pair displacement; ``check_pairs``: held
    out, only reported."""

    pairs: PairsFileCfg | list[PairRow] = Field(
        description="The control points: rows [x, y, z, X, Y, Z] (a source point and where it "
        "goes), or {file: CSV/TXT with a header}")
    columns: Annotated[list[str], Field(min_length=6, max_length=6)] | None = Field(
        default=None, description="The file header's names of x, y, z, X, Y, Z (null: those "
        "six names)")
    smoothing: float = Field(default=0.0, ge=0, le=MAX_VALUE, description="0 interpolates the "
                             "pairs; larger values smooth, with scipy RBFInterpolator's "
                             "meaning (data units)")
    tolerance: float = Field(default=1e-6, gt=0, lt=1, description="The largest pair residual "
                             "allowed, relative to the largest pair displacement")
    check_pairs: PairsFileCfg | list[PairRow] | None = Field(
        default=None, description="Held-out pairs, not fitted: only their error is reported")

    @field_validator("pairs", "check_pairs", mode="before")
    @classmethod
    def _bounded(cls, v):   # before any row is validated: a 2 MB config holds ~140,000 rows
        from splatdeform.deform.points import MAX_PAIRS  # not at import: the deform layer

        if isinstance(v, list) and len(v) > MAX_PAIRS:
            raise ValueError(f"{len(v):,} inline pairs exceed the limit of {MAX_PAIRS:,} (the "
                             "dense fit: O(m^3) time, 8 m^2 bytes)")
        return v
