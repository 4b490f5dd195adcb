"""The local web editor (``splatdeform edit``): a plain controller (:mod:`.controller`, usable
from a notebook) and the WebGL2 page (:mod:`.page_server`, imported only by the verb)."""

from __future__ import annotations

from .controller import EditorController
from .frames import Frame
from .saving import SaveResult
from .state import HandleState, StaleFitError

__all__ = ["EditorController", "Frame", "HandleState", "SaveResult", "StaleFitError"]
