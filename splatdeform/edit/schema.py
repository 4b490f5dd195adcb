"""The base of every config model and the field types they share (one definition each).

Numbers in a config are finite and bounded, and a boolean is not a number (``min: true`` would
otherwise read as 1): :data:`Number` (coordinates, translations, pivots, matrix entries,
selector numbers: within +-:data:`MAX_VALUE`), :data:`Real` (any finite float64: property
values), :data:`Index` (a non-negative integer). A YAML integer too long to be a config number
arrives as a :class:`LongInt` (see :mod:`splatdeform.edit.config`'s loader) and is refused by
whichever key holds it.
"""

from __future__ import annotations

import math
import re
import sys
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field

MAX_INDEX = 2**62  # point indices beyond any real model (and inside int64)
MAX_VALUE = 1e15  # coordinates, translations, pivots, matrix entries (the LAS coordinate bound)
MAX_REAL = sys.float_info.max  # property values: any finite float64
MAX_INT_DIGITS = 1000  # a YAML integer longer than this is no config number (float64 < 1e309)


class LongInt:
    """A YAML integer of more than :data:`MAX_INT_DIGITS` digits, kept as its length: never
    converted (Python refuses str -> int beyond 4,300 digits, and the conversion is quadratic),
    so the key that holds it is refused by validation with one line."""

    __slots__ = ("digits",)

    def __init__(self, digits: int) -> None:
        self.digits = digits

    def __repr__(self) -> str:
        return f"an integer of {self.digits:,} digits"

    __str__ = __repr__


def shown(value: Any, limit: int = 60) -> str:
    """``repr(value)`` for a message, at most about ``limit`` characters (a huge integer or a
    long string is shortened, never converted in full)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 200:
        if value.bit_length() < 10_000:  # str() is safe (and quick) below 3,000 digits
            return f"an integer of {len(str(abs(value))):,} digits"
        return f"an integer of about {int(value.bit_length() * math.log10(2)) + 1:,} digits"
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 20]}... ({len(text):,} characters)"


#: a number given as text must be a plain decimal one (YAML 1.1 and Python's float() also read
#: ``1_0.5`` as 10.5, ``0x10`` as 16); the PLY reader and pairs files read numbers the same way
_PLAIN_NUMBER = re.compile(r"\s*[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?\s*")


def _not_bool(value: Any) -> Any:
    if isinstance(value, bool):
        raise ValueError(f"expected a number, got {str(value).lower()} (a boolean)")
    if isinstance(value, str) and not _PLAIN_NUMBER.fullmatch(value):
        raise ValueError(f"expected a plain decimal number, got {shown(value)}")
    return value


def _range(bound: float) -> str:
    return "a finite number" if bound >= MAX_REAL else f"a number within +-{bound:g}"


def _before(bound: float):
    def check(value: Any) -> Any:
        value = _not_bool(value)
        if isinstance(value, LongInt) or (isinstance(value, int) and abs(value) > bound):
            raise ValueError(f"expected {_range(bound)}, got {shown(value)}")
        return value

    return BeforeValidator(check)


def _after(bound: float):
    def check(value: float) -> float:
        if not math.isfinite(value):
            raise ValueError(f"expected a finite number, got {value}")
        if abs(value) > bound:
            raise ValueError(f"expected {_range(bound)}, got {value:g}")
        return value

    return AfterValidator(check)


Number = Annotated[float, _before(MAX_VALUE), _after(MAX_VALUE)]
Real = Annotated[float, _before(MAX_REAL), _after(MAX_REAL)]
Index = Annotated[int, BeforeValidator(_not_bool), Field(ge=0, le=MAX_INDEX)]
Vec3 = Annotated[list[Number], Field(min_length=3, max_length=3)]


class Strict(BaseModel):
    """Unknown keys, NaN and infinities are errors."""

    model_config = ConfigDict(extra="forbid", strict=False, allow_inf_nan=False)
