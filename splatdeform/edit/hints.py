"""'Did you mean' for config validation errors: the key names the config models allow where
an unknown key sits, and the values a Literal allows (difflib, :mod:`splatdeform.suggest`)."""

from __future__ import annotations

import re
import types
from typing import Annotated, Any, Union, get_args, get_origin

from pydantic import BaseModel

from splatdeform.suggest import did_you_mean


def _members(tp: Any) -> list[Any]:
    """The alternatives of a type: Annotated unwrapped, unions flattened."""
    origin = get_origin(tp)
    if origin is Annotated:
        return _members(get_args(tp)[0])
    if origin is Union or origin is types.UnionType:
        return [m for arg in get_args(tp) for m in _members(arg)]
    return [tp]


def _step(tps: list[Any], part: Any) -> list[Any]:
    """The types at ``part`` (a key or a list index) below any of ``tps``; a part no type
    has (pydantic's label of a union member, e.g. 'box selector') leaves them as they are."""
    out = []
    for tp in (m for t in tps for m in _members(t)):
        origin, args = get_origin(tp), get_args(tp)
        if isinstance(part, int) and origin in (list, tuple) and args:
            out.append(args[part] if origin is tuple and ... not in args
                       and part < len(args) else args[0])
        elif isinstance(part, str) and isinstance(tp, type) and issubclass(tp, BaseModel):
            if tp.__name__ == part:
                out.append(tp)
            out.extend(f.annotation for n, f in tp.model_fields.items()
                       if part in (n, f.alias))
        elif isinstance(part, str) and origin is dict and len(args) == 2:
            out.append(args[1])
    return out or tps


def _model(title: str, roots: tuple[type[BaseModel], ...]) -> type[BaseModel] | None:
    todo = list(roots)
    while todo:
        cls = todo.pop()
        if cls.__name__ == title:
            return cls
        todo.extend(cls.__subclasses__())
    return None


def hint(err: dict[str, Any], title: str, roots: tuple[type[BaseModel], ...]) -> str:
    """`` (did you mean 'rotate'?)`` for an unknown key (``err``, one of pydantic's errors of
    the model named ``title``, a subclass of ``roots``) or a Literal's value; else ''."""
    kind, got = err["type"], err.get("input")
    if kind == "literal_error" and isinstance(got, str):
        allowed = re.findall(r"'([^']*)'", (err.get("ctx") or {}).get("expected", ""))
        return did_you_mean(got, allowed)
    if kind == "selector" and isinstance(got, dict):  # {boxx: ...}: one unknown kind
        kinds = re.search(r"one of ([\w, ]+)$", err["msg"])
        unknown = [str(k) for k in got if kinds and k not in kinds[1].split(", ")]
        found = did_you_mean(unknown[0], kinds[1].split(", ")) if len(unknown) == 1 else ""
        return f" (got {unknown[0]!r}){found}" if found else ""
    root = _model(title, roots)
    if kind != "extra_forbidden" or root is None or not err["loc"]:
        return ""
    tps: list[Any] = [root]
    for part in err["loc"][:-1]:
        tps = _step(tps, part)
    names = {f.alias or n for tp in tps for m in _members(tp)
             if isinstance(m, type) and issubclass(m, BaseModel)
             for n, f in m.model_fields.items()}
    return did_you_mean(str(err["loc"][-1]), sorted(names))
