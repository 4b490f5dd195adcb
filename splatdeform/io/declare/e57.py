"""E57 (pye57 over libE57Format; :mod:`splatdeform.io.e57`): the file header checked against
the size, and the scans' point counts from the XML section, are the probe (no pye57 import).
Not streamable: over the budget an E57 file is refused. Scanner data: z-up, like LiDAR."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from ..format import FileCost, Format

if TYPE_CHECKING:
    from ...model import PointModel

#: decoded bytes per point: the records (up to ~10 fields of 1-8 bytes), float64 world
#: positions twice (the model's and a scan's while it is built) and the valid mask
E57_POINT_BYTES = 120


def probe(path: Path, head: bytes, size: int, file: Path | None = None) -> FileCost:
    """The scans' declared points from the XML section (``file``); an archive member, judged
    before extraction, from its size (a point takes at least 4 bytes of compressed data)."""
    from ..e57 import HEADER_SIZE, check_header, file_points

    check_header(path, head[:HEADER_SIZE], size)
    points = sum(file_points(file)) if file is not None else max(size // 4, 1)
    return FileCost(points, size, E57_POINT_BYTES, size + points * E57_POINT_BYTES)


def fields(path: Path) -> dict:
    """``info``'s E57 fields: the version and each scan (name, points, valid points, pose,
    grid, fields)."""
    from ..e57 import read_source

    source = read_source(path)
    return {"format": source.format_name, "format_fields": {
        "scans": len(source.scans), "coordinate_metadata": source.coordinate_metadata or "none"}}


def convert(model: PointModel, ext: str) -> PointModel:
    """An E57-read model written as another format: its fields as a PLY's (a PLY output keeps
    every field, x y z in the world frame, and the scan index), else none."""
    from ..e57 import ply_source_from_e57

    return replace(model, source=ply_source_from_e57(model.source) if ext == ".ply" else None)


FORMATS = {".e57": Format("e57", "path", writer="e57_write", probe=probe, fields=fields,
                          convert=convert, lidar=True)}
