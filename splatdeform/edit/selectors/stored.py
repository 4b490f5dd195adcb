"""The stored form of a plain selector (in a saved field's JSON ``meta``), built back from a
fixed table by kind name: a file never names code to import.

``{"box": {"min": [3], "max": [3], "origin": [3] | null, "scale": [3] | null}}``,
``{"plane": {"point", "normal", "origin", "scale"}}``, ``{"sphere": {"center", "radius"}}``,
``{"property": {"name", "equals"?, "in"?, "min"?, "max"?}}``, ``{"all": [selector, ...]}``,
``{"not": selector}`` and ``{"indices": "stored"}``: an indices selector keeps no list and
no file name in the meta; the region's point indices are stored beside it as an array (the
field's ``fixed_idx`` / ``handle_idx_<j>``), so reading a field never opens a path it names.

:func:`decode` checks every key and type (numbers finite, boxes ordered, normals non-zero, at
most :data:`MAX_DEPTH` levels and :data:`MAX_NODES` selectors) and raises
:class:`StoredError` naming the key; :func:`from_v1` translates the stored form of fields
written before (``{"__selector__": "splatdeform.edit.selectors.box:Box", ...}``) by a fixed
table of the names those versions wrote, nothing else.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from splatdeform.edit.selectors.all_of import All
from splatdeform.edit.selectors.box import Box
from splatdeform.edit.selectors.indices import Indices
from splatdeform.edit.selectors.not_ import Not
from splatdeform.edit.selectors.plane import Plane
from splatdeform.edit.selectors.prop import Property
from splatdeform.edit.selectors.sphere import Sphere

MAX_DEPTH = 16  # all/not nesting
MAX_NODES = 1000  # selectors in one region, nested ones counted
MAX_VALUES = 100_000  # a property's `in` list
MAX_NAME = 256  # a property name
STORED_INDICES = "stored"  # {"indices": "stored"}: the region's indices are an array member
MAX_COORD = 1e300  # a coordinate beyond this overflows the first arithmetic


class StoredError(ValueError):
    """A stored selector that is not one: ``key`` (``fixed[0].box.min``) and what was wrong."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key


def encode(sel: Any) -> dict:
    """The stored form of a plain selector (see the module)."""
    if isinstance(sel, Box):
        return {"box": {"min": _floats(sel.min), "max": _floats(sel.max),
                        "origin": _floats(sel.origin), "scale": _floats(sel.scale)}}
    if isinstance(sel, Plane):
        return {"plane": {"point": _floats(sel.point), "normal": _floats(sel.normal),
                          "origin": _floats(sel.origin), "scale": _floats(sel.scale)}}
    if isinstance(sel, Sphere):
        return {"sphere": {"center": _floats(sel.center), "radius": float(sel.radius)}}
    if isinstance(sel, Property):
        return sel.to_config()
    if isinstance(sel, All):
        return {"all": [encode(p) for p in sel.parts]}
    if isinstance(sel, Not):
        return {"not": encode(sel.part)}
    if isinstance(sel, Indices):
        return {"indices": STORED_INDICES}
    raise TypeError(f"no stored form for {type(sel).__name__}")


def _floats(v) -> list[float] | None:
    return None if v is None else [float(x) for x in v]


# ------------------------------------------------------------------------------ reading

def _number(v: Any, key: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise StoredError(key, f"expected a number, got {_kind(v)}")
    try:
        f = float(v)
    except OverflowError:
        f = math.inf
    if not math.isfinite(f) or abs(f) > MAX_COORD:
        raise StoredError(key, f"expected a finite number, got {_short(v)}")
    return f


def _vec3(v: Any, key: str) -> tuple[float, float, float]:
    if not isinstance(v, list) or len(v) != 3:
        raise StoredError(key, f"expected a list of 3 numbers, got {_kind(v)}")
    a, b, c = (_number(x, f"{key}[{i}]") for i, x in enumerate(v))
    return a, b, c


def _frame(body: dict, key: str) -> tuple[tuple | None, tuple | None]:
    origin, scale = body.get("origin"), body.get("scale")
    if (origin is None) != (scale is None):
        raise StoredError(key, "expected both origin and scale, or neither")
    if origin is None:
        return None, None
    o, s = _vec3(origin, f"{key}.origin"), _vec3(scale, f"{key}.scale")
    if not all(x > 0 for x in s):
        raise StoredError(f"{key}.scale", f"expected positive numbers, got {list(s)}")
    return o, s


def _body(v: Any, key: str, required: tuple[str, ...], optional: tuple[str, ...]) -> dict:
    if not isinstance(v, dict):
        raise StoredError(key, f"expected a mapping, got {_kind(v)}")
    unknown = [k for k in v if k not in required + optional]
    if unknown:
        raise StoredError(key, f"unknown key {str(unknown[0])[:40]!r} (expected "
                          f"{', '.join(required + optional)})")
    missing = [k for k in required if k not in v]
    if missing:
        raise StoredError(f"{key}.{missing[0]}", "required key is missing")
    return v


def _box(v: Any, key: str, _count: list) -> Box:
    b = _body(v, key, ("min", "max"), ("origin", "scale"))
    lo, hi = _vec3(b["min"], f"{key}.min"), _vec3(b["max"], f"{key}.max")
    if any(x > y for x, y in zip(lo, hi, strict=True)):
        raise StoredError(key, f"min {list(lo)} exceeds max {list(hi)}")
    origin, scale = _frame(b, key)
    return Box(lo, hi, origin, scale)


def _plane(v: Any, key: str, _count: list) -> Plane:
    b = _body(v, key, ("point", "normal"), ("origin", "scale"))
    point, normal = _vec3(b["point"], f"{key}.point"), _vec3(b["normal"], f"{key}.normal")
    if not np.linalg.norm(normal) > 0:
        raise StoredError(f"{key}.normal", "expected a non-zero vector")
    origin, scale = _frame(b, key)
    return Plane(point, normal, origin, scale)


def _sphere(v: Any, key: str, _count: list) -> Sphere:
    b = _body(v, key, ("center", "radius"), ())
    radius = _number(b["radius"], f"{key}.radius")
    if not radius > 0:
        raise StoredError(f"{key}.radius", f"expected a positive number, got {radius}")
    return Sphere(_vec3(b["center"], f"{key}.center"), radius)


def _property(v: Any, key: str, _count: list) -> Property:
    b = _body(v, key, ("name",), ("equals", "in", "min", "max"))
    name = b["name"]
    if not isinstance(name, str) or not 0 < len(name) <= MAX_NAME:
        raise StoredError(f"{key}.name", f"expected a property name (1 to {MAX_NAME} "
                          f"characters), got {_kind(name)}")
    values = b.get("in")
    if values is not None:
        if not isinstance(values, list) or not 0 < len(values) <= MAX_VALUES:
            raise StoredError(f"{key}.in", f"expected a list of 1 to {MAX_VALUES:,} numbers, "
                              f"got {_kind(values)}")
        values = tuple(_number(x, f"{key}.in[{i}]") for i, x in enumerate(values))
    bounds = {k: None if b.get(k) is None else _number(b[k], f"{key}.{k}")
              for k in ("equals", "min", "max")}
    if values is None and all(x is None for x in bounds.values()):
        raise StoredError(key, "expected at least one of equals, in, min, max")
    if bounds["min"] is not None and bounds["max"] is not None and bounds["min"] > bounds["max"]:
        raise StoredError(key, f"min {bounds['min']} exceeds max {bounds['max']}")
    return Property(name, bounds["equals"], values, bounds["min"], bounds["max"])


def _all(v: Any, key: str, count: list) -> All:
    if not isinstance(v, list) or not v:
        raise StoredError(key, f"expected a non-empty list of selectors, got {_kind(v)}")
    return All(tuple(_decode(p, f"{key}[{i}]", count) for i, p in enumerate(v)))


def _not(v: Any, key: str, count: list) -> Not:
    return Not(_decode(v, key, count))


def _indices(v: Any, key: str, _count: list) -> Indices:
    if v != STORED_INDICES:
        raise StoredError(key, f"expected {STORED_INDICES!r} (a field keeps the region's indices "
                          "as an array, never a list or a file name), got " + _kind(v))
    return Indices()


#: kind name -> builder; the only selectors a stored form can make (one per REGISTRY name)
KINDS = {"box": _box, "sphere": _sphere, "plane": _plane, "indices": _indices,
         "property": _property, "all": _all, "not": _not}


def _decode(v: Any, key: str, count: list) -> Any:
    count[0] += 1
    if count[0] > MAX_NODES:
        raise StoredError(key, f"more than {MAX_NODES} selectors")
    if key.count(".all") + key.count(".not") > MAX_DEPTH:
        raise StoredError(key, f"selectors nested deeper than {MAX_DEPTH}")
    if not isinstance(v, dict) or len(v) != 1:
        raise StoredError(key, "expected a mapping with exactly one of " + ", ".join(KINDS)
                          + f", got {_kind(v)}")
    (kind, body), = v.items()
    build = KINDS.get(kind) if isinstance(kind, str) else None
    if build is None:
        raise StoredError(key, f"unknown selector kind {str(kind)[:40]!r} (expected one of "
                          f"{', '.join(KINDS)})")
    return build(body, f"{key}.{kind}", count)


def decode(value: Any, key: str) -> list:
    """A region's stored selectors (a list) -> plain selectors; StoredError naming the key."""
    if not isinstance(value, list):
        raise StoredError(key, f"expected a list of selectors, got {_kind(value)}")
    count = [0]
    return [_decode(v, f"{key}[{i}]", count) for i, v in enumerate(value)]


def has_indices(sels: list) -> bool:
    """Whether any leaf of the selectors is an indices selector."""
    from splatdeform.edit.selectors import leaves

    return any(isinstance(leaf, Indices) for s in sels for leaf in leaves(s))


# ------------------------------------------------------------------ fields of version 1

#: the ``__selector__`` names version 1 wrote, and their kind
V1_NAMES = {"splatdeform.edit.selectors.box:Box": "box",
            "splatdeform.edit.selectors.sphere:Sphere": "sphere",
            "splatdeform.edit.selectors.plane:Plane": "plane",
            "splatdeform.edit.selectors.indices:Indices": "indices",
            "splatdeform.edit.selectors.prop:Property": "property",
            "splatdeform.edit.selectors.all_of:All": "all",
            "splatdeform.edit.selectors.not_:Not": "not"}
_V1_FIELDS = {"box": ("min", "max", "origin", "scale"), "plane": ("point", "normal", "origin",
                                                                   "scale"),
              "sphere": ("center", "radius"), "property": ("name", "equals", "values", "min",
                                                           "max"),
              "indices": ("indices", "file"), "all": ("parts",), "not": ("part",)}


def _v1(v: Any, key: str, depth: int) -> Any:
    if depth > MAX_DEPTH:
        raise StoredError(key, f"selectors nested deeper than {MAX_DEPTH}")
    if not isinstance(v, dict) or "__selector__" not in v:
        raise StoredError(key, f"expected a stored selector, got {_kind(v)}")
    name = v["__selector__"]
    kind = V1_NAMES.get(name) if isinstance(name, str) else None
    if kind is None:
        raise StoredError(f"{key}.__selector__", f"unknown selector {str(name)[:80]!r}; "
                          "re-save the field with this version (deform --save-field)")
    body = {k: x for k, x in v.items() if k != "__selector__"}
    unknown = [k for k in body if k not in _V1_FIELDS[kind]]
    if unknown:
        raise StoredError(key, f"unknown key {str(unknown[0])[:40]!r} for {kind}")
    if kind == "all":
        parts = body.get("parts")
        if not isinstance(parts, list):
            raise StoredError(f"{key}.parts", f"expected a list, got {_kind(parts)}")
        return {"all": [_v1(p, f"{key}.parts[{i}]", depth + 1) for i, p in enumerate(parts)]}
    if kind == "not":
        return {"not": _v1(body.get("part"), f"{key}.part", depth + 1)}
    if kind == "indices":  # version 1 stored the region's indices too; a file is not followed
        return {"indices": STORED_INDICES}
    if kind == "property":
        body = {("in" if k == "values" else k): x for k, x in body.items() if x is not None}
    return {kind: body}


def from_v1(value: Any, key: str) -> list:
    """A region's selectors as version 1 stored them -> the stored form of this version."""
    if not isinstance(value, list):
        raise StoredError(key, f"expected a list of selectors, got {_kind(value)}")
    if len(value) > MAX_NODES:
        raise StoredError(key, f"more than {MAX_NODES} selectors")
    return [_v1(v, f"{key}[{i}]", 0) for i, v in enumerate(value)]


def _kind(v: Any) -> str:
    """What a JSON value is, in a few words (never its whole content)."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return f"a boolean ({v})"
    if isinstance(v, (int, float)):
        return f"a number ({_short(v)})"
    if isinstance(v, str):
        return repr(v) if len(v) <= 40 and v.isprintable() else \
            f"a string of {len(v)} characters"
    if isinstance(v, list):
        return f"a list of {len(v)}"
    if isinstance(v, dict):
        return f"a mapping of {len(v)} keys"
    return type(v).__name__


def _short(v: Any) -> str:
    return repr(v)[:40]
