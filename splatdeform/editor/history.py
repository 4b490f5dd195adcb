"""Undo / redo for the editor: snapshots of the controller's regions and poses (no web imports).

A snapshot is the fixed selectors, per handle its selectors and (4, 4) pose, and the curve (an
immutable :class:`~.curve.CurveState`, its moved points included) and the Gaussians'
covariance mode. Selectors are immutable
values, so a snapshot is a few small lists. Restoring one that matches the last fit's
regions makes that fit current again (the controller compares region keys), so undoing a wrong
grab never throws away a fit.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .controller import EditorController, HandleState


def snapshot(ed: EditorController) -> tuple[Any, ...]:
    """The controller's editable state as an immutable-enough value."""
    return (list(ed.fixed), [(list(h.selectors), h.matrix.copy()) for h in ed.handles],
            ed.curve, ed.settings.gaussians.covariance)


def restore(ed: EditorController, snap: tuple[Any, ...]) -> None:
    fixed, handles, curve, covariance = snap
    ed.fixed = list(fixed)
    ed.handles = [HandleState(list(s), m.copy()) for s, m in handles]
    ed.curve = curve
    ed.settings.gaussians.covariance = covariance


def _same(a: tuple[Any, ...], b: tuple[Any, ...]) -> bool:
    if a[0] != b[0] or len(a[1]) != len(b[1]) or a[2:] != b[2:]:
        return False
    return all(sa == sb and np.array_equal(ma, mb)
               for (sa, ma), (sb, mb) in zip(a[1], b[1], strict=True))


@dataclass
class History:
    """Linear undo/redo over controller snapshots; :meth:`record` after every change."""

    ed: EditorController
    limit: int = 200
    undo_stack: list[tuple[Any, ...]] = field(default_factory=list)
    redo_stack: list[tuple[Any, ...]] = field(default_factory=list)
    current: tuple[Any, ...] | None = None

    def __post_init__(self) -> None:
        self.current = snapshot(self.ed)

    def record(self) -> None:
        """Call after a change: the previous state becomes undoable (no-op if unchanged)."""
        now = snapshot(self.ed)
        if self.current is not None and _same(now, self.current):
            return
        self.undo_stack.append(self.current)
        del self.undo_stack[:-self.limit]
        self.redo_stack.clear()
        self.current = now

    def undo(self) -> bool:
        if not self.undo_stack:
            return False
        self.redo_stack.append(snapshot(self.ed))
        self.current = self.undo_stack.pop()
        restore(self.ed, self.current)
        return True

    def redo(self) -> bool:
        if not self.redo_stack:
            return False
        self.undo_stack.append(snapshot(self.ed))
        self.current = self.redo_stack.pop()
        restore(self.ed, self.current)
        return True
