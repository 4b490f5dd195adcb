"""XYZ/PTS text (Open3D): no header, so no probe (judged from the size,
:func:`splatdeform.io.format.size_cost`)."""

from __future__ import annotations

from ..format import Format

_TEXT = Format("open3d_io", "path")
FORMATS = {".xyz": _TEXT, ".xyzn": _TEXT, ".pts": _TEXT}
