"""The base of every config model and the field types they share (one definition each)."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
MAX_INDEX = 2**62  # point indices beyond any real model (and inside int64)


class Strict(BaseModel):
    """Unknown keys, NaN and infinities are errors."""

    model_config = ConfigDict(extra="forbid", strict=False, allow_inf_nan=False)
