"""The page's control-point pair actions (no web imports): add, move and remove a pair of a
``points:`` edit, and remove a handle. :mod:`.session` puts :data:`OPS` in its table.

Pairs stay in the edit's units (``regions.units``) as the YAML gave them; the page sends local
model coordinates (model minus ``controller.origin``), converted here. An edit that read its
pairs from a file (``points.pairs: {file: ...}``) holds them inline from its first change on:
Save writes the edited pairs inline in ``points.pairs`` and never writes the pairs file (it is
an input); the page says so once. ``check_pairs`` and ``columns`` stay as they were.

Every change is checked before it is made and refused in one line, changing nothing: an index
that is not a whole number of the pairs (or handles), coordinates that are not 3 finite numbers,
more than :data:`~splatdeform.deform.points.MAX_PAIRS` pairs, and what ``deform`` refuses of
the pairs themselves (duplicate or conflicting sources, a pair far outside the model's box:
:func:`~splatdeform.deform.points.check_pairs`). With a current fit, a pair change refits at
once (the pairs are constraints of the fit); a change that fit refuses is undone and refused
with the fit's line. Undo / redo go through the session's history (the pairs are in the
controller's snapshot).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from splatdeform.deform.points import MAX_PAIRS, Pairs, check_pairs
from splatdeform.edit import units as u
from splatdeform.edit.config import PairsFileCfg, PointsCfg, validation_error
from splatdeform.edit.schema import Strict

from ..errors import InputError

KEY = "points.pairs"


def rows_of(points: PointsCfg, base_dir: Path) -> np.ndarray:
    """(n, 6) float64 rows [x, y, z, X, Y, Z] of ``points.pairs`` in the edit's units (a pairs
    file read as ``deform`` reads it)."""
    if isinstance(points.pairs, PairsFileCfg):
        from splatdeform.edit.metaphors.points import read_pairs_file

        return read_pairs_file(base_dir / points.pairs.file, points.columns, KEY)[0]
    return np.asarray(points.pairs, dtype=np.float64).reshape(-1, 6)


def model_pairs(points: PointsCfg, units: str, model, base_dir: Path) -> Pairs:
    """``points.pairs`` in model units (what the fit uses)."""
    from splatdeform.edit.metaphors.points import load_pairs

    return load_pairs(points.pairs, points.columns, KEY, units, model, base_dir)


def _index(req: dict[str, Any], key: str, n: int, what: str) -> int:
    """``req[key]``: a whole number 0 <= i < n, else one line naming it."""
    i = req.get(key)
    if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < n:
        have = f"the edit has {n} {what}{'' if n == 1 else 's'}"
        raise InputError(f"{key}: expected a {what} index 0..{n - 1} ({have}), got "
                         f"{str(i)[:40]}" if n else f"{key}: {have}")
    return i


def _point(req: dict[str, Any], key: str) -> np.ndarray | None:
    """``req[key]``: 3 finite local coordinates (None when absent)."""
    v = req.get(key)
    if v is None:
        return None
    ok = isinstance(v, list) and len(v) == 3 and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
    a = np.asarray(v, dtype=np.float64) if ok else np.zeros(0)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise InputError(f"{key}: expected 3 finite numbers (local coordinates), got "
                         f"{str(v)[:80]}")
    return a


class PairEdits:
    """The pair actions over one session (its controller ``ed``; see the module docstring)."""

    def __init__(self, session: Any) -> None:
        self.s = session

    @property
    def ed(self):
        return self.s.ed

    def _to_units(self, local: np.ndarray) -> np.ndarray:
        """Local coordinates (3,) as a point in the edit's units."""
        model = local + self.ed.origin
        if self.ed.units == "relative":
            frame = u.Frame.of(self.ed.model)
            return (model - frame.origin) / frame.extent
        return model

    def rows(self) -> np.ndarray:
        if self.ed.points is None:
            return np.zeros((0, 6))
        return rows_of(self.ed.points, self.ed.base_dir)

    def _set_rows(self, rows: np.ndarray) -> None:
        """Replace the pairs by ``rows`` (n, 6) in the edit's units (inline), after the checks
        ``deform`` makes of them; n == 0 removes ``points:``."""
        ed = self.ed
        if rows.shape[0] > MAX_PAIRS:
            raise InputError(f"{KEY}: at most {MAX_PAIRS:,} pairs in one edit (the dense fit: "
                             "O(m^3) time, 8 m^2 bytes); remove some first")
        if rows.shape[0] == 0:
            if ed.points is not None and ed.points.check_pairs is not None:
                raise InputError(f"{KEY}: the last pair; the edit's points.check_pairs need "
                                 "fitted pairs (add another pair first)")
            ed.set_points(None)
            self.s.message = "points: the last pair removed; the edit has no pairs now"
            return
        old = ed.points
        was_file = old is not None and isinstance(old.pairs, PairsFileCfg)
        base = {} if old is None else old.model_dump(exclude_none=True)
        base["pairs"] = rows.tolist()
        if not isinstance(base.get("check_pairs"), dict):
            base.pop("columns", None)   # no file left to name columns of
        try:
            new = PointsCfg.model_validate(base)
        except ValidationError as exc:   # a number past the config's bound
            raise validation_error("request", exc, "points", (Strict,)) from None
        pairs = model_pairs(new, ed.units, ed.model, ed.base_dir)
        lo, hi = ed.model.bbox()
        check_pairs(pairs, lo, hi, anchored=True)  # too few pairs: the fit's line, at Fit
        ed.set_points(new)
        if was_file:
            self.s.message = (f"{KEY}: edited; Save writes the pairs inline in the YAML "
                              f"({old.pairs.file} is not changed)")

    def _change(self, rows: np.ndarray) -> None:
        """``_set_rows`` and, when the fit was current, a refit; refused: nothing changed."""
        ed = self.ed
        live = not ed.stale
        before = ed.snapshot()
        self._set_rows(rows)
        if live and ed.points is not None:
            try:
                self.s.refit()
            except Exception:
                ed.restore(before)
                raise

    # ---- actions ------------------------------------------------------------------------
    def add(self, req: dict[str, Any]) -> None:
        """A pair at local ``source`` going to local ``target`` (default: the source)."""
        src = _point(req, "source")
        if src is None:
            raise InputError("source: expected 3 finite numbers (local coordinates)")
        dst = _point(req, "target")
        rows = self.rows()
        if rows.shape[0] >= MAX_PAIRS:
            raise InputError(f"{KEY}: at most {MAX_PAIRS:,} pairs in one edit (the dense fit: "
                             "O(m^3) time, 8 m^2 bytes); remove some first")
        row = np.concatenate([self._to_units(src), self._to_units(src if dst is None else dst)])
        self._change(np.vstack([rows, row[None]]))

    def move(self, req: dict[str, Any]) -> None:
        """Pair ``index``'s ``source`` and / or ``target`` (local coordinates)."""
        rows = self.rows()
        i = _index(req, "index", rows.shape[0], "pair")
        src, dst = _point(req, "source"), _point(req, "target")
        if src is None and dst is None:
            raise InputError("move_pair: expected a source or a target (3 finite numbers)")
        rows = rows.copy()
        if src is not None:
            rows[i, :3] = self._to_units(src)
        if dst is not None:
            rows[i, 3:] = self._to_units(dst)
        self._change(rows)

    def remove(self, req: dict[str, Any]) -> None:
        """Pair ``index`` removed (the last one removes ``points:``)."""
        rows = self.rows()
        i = _index(req, "index", rows.shape[0], "pair")
        self._change(np.delete(rows, i, axis=0))

    def remove_handle(self, req: dict[str, Any]) -> None:
        """Handle ``handle`` and its pose removed (an edit keeps at least one)."""
        h = _index(req, "handle", len(self.ed.handles), "handle")
        self.ed.remove_handle(h)


def _op(name: str) -> Callable[[Any, dict[str, Any]], None]:
    return lambda session, req: getattr(PairEdits(session), name)(req)


#: op -> handler(session, request), merged into :data:`.session.Session.OPS`
OPS: dict[str, Callable[[Any, dict[str, Any]], None]] = {
    "add_pair": _op("add"), "move_pair": _op("move"), "remove_pair": _op("remove"),
    "remove_handle": _op("remove_handle"),
}
