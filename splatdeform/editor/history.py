"""Undo / redo for the editor: snapshots of the controller's regions and poses (no web imports).

A snapshot (:class:`~.state.Snapshot`, from :meth:`EditorController.snapshot`) is the fixed
selectors, per handle its selectors and (4, 4) pose, the curve (an immutable
:class:`~.curve.CurveState`, its moved points included), the Gaussians' covariance mode and
the control-point pairs (the ``points:`` config, replaced whole on a change).
Selectors are immutable values, so a snapshot is a few small tuples; it comes back through
:meth:`EditorController.restore`. Restoring one that matches the last fit's
regions makes that fit current again (the controller compares region keys), so undoing a wrong
grab never throws away a fit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .controller import EditorController
from .state import Snapshot


@dataclass
class History:
    """Linear undo/redo over controller snapshots; :meth:`record` after every change."""

    ed: EditorController
    limit: int = 200
    undo_stack: list[Snapshot] = field(default_factory=list)
    redo_stack: list[Snapshot] = field(default_factory=list)
    current: Snapshot | None = None

    def __post_init__(self) -> None:
        self.current = self.ed.snapshot()

    def record(self) -> None:
        """Call after a change: the previous state becomes undoable (no-op if unchanged)."""
        now = self.ed.snapshot()
        if now.same(self.current):
            return
        self.undo_stack.append(self.current)
        del self.undo_stack[:-self.limit]
        self.redo_stack.clear()
        self.current = now

    def undo(self) -> bool:
        if not self.undo_stack:
            return False
        self.redo_stack.append(self.ed.snapshot())
        self.current = self.undo_stack.pop()
        self.ed.restore(self.current)
        return True

    def redo(self) -> bool:
        if not self.redo_stack:
            return False
        self.undo_stack.append(self.ed.snapshot())
        self.current = self.redo_stack.pop()
        self.ed.restore(self.current)
        return True
