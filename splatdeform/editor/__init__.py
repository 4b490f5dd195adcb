"""The local web editor: a plain controller (:mod:`.controller`) and a viser front end
(:mod:`.server`, imported only by ``splatdeform edit``)."""

from __future__ import annotations

from .controller import EditorController, Frame, HandleState, SaveResult, StaleFitError

__all__ = ["EditorController", "Frame", "HandleState", "SaveResult", "StaleFitError"]
