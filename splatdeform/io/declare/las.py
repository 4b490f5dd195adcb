"""LAS/LAZ (laspy): the header :mod:`splatdeform.io.las_header` validates against the file
size is the probe (the same checks ``info`` and the loader run: a corrupt VLR count or point
count is one FormatError line, before laspy sees the file). LiDAR: z-up, elevation colours."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from ..format import FileCost, Format

if TYPE_CHECKING:
    from ...model import PointModel

#: lazrs's parallel decompressor (the whole-file load) holds decompressed LAZ chunks beside the
#: points asked for, and the compressed bytes it read: per chunk point, about this many records
#: (measured: a 3M-point LAZ written as one chunk, 30-byte records, 67 MB compressed, read 12,000
#: points at a time, peaked 276 MB above the interpreter: 67 MB + 2.3 x 90 MB).
LAZ_PARALLEL_COPIES = 2.5


def laz_reader_bytes(compressed_bytes: int, chunk_points: int, record: int,
                     parallel: bool = False) -> int:
    """What a LAZ reader holds besides the rows it returns: the sequential decompressor (the
    streamed reads) one compressed chunk (at most the whole compressed point data, at most
    ``chunk_points`` raw records when the chunk size is known); the parallel one (a whole load)
    also the decompressed chunks (:data:`LAZ_PARALLEL_COPIES`)."""
    chunk_bytes = compressed_bytes if chunk_points <= 0 else \
        min(compressed_bytes, chunk_points * record)
    if not parallel:
        return chunk_bytes
    points = chunk_points if chunk_points > 0 else compressed_bytes * 64 // max(record, 1)
    return chunk_bytes + int(LAZ_PARALLEL_COPIES * points * record)


def probe(path: Path, head: bytes, size: int, file: Path | None = None) -> FileCost:
    """The point records (decompressed for LAZ, which holds 3-10x more points than its size
    suggests), their decoded columns, and for LAZ the decompressor's buffers
    (:func:`laz_reader_bytes`)."""
    from ..las_header import check_header_bytes

    layout = check_header_bytes(path, head, size)
    points, record = layout.point_count, layout.record_length
    record_bytes = record + 24 + 8   # raw record, float64 positions, decoded attributes
    load = 3 * points * record + points * 32 + size
    reader = 0
    if layout.compressed:
        data = max(size - layout.offset_to_points, 0)
        chunk = min(layout.laz_chunk_points or points, points)
        load += laz_reader_bytes(data, chunk, record, parallel=True)
        reader = laz_reader_bytes(data, chunk, record)
    return FileCost(points, size, record_bytes, load, reader)


def convert(model: PointModel, ext: str) -> PointModel:
    """A LAS-read model written as another format: its source as a PLY's (a PLY output keeps
    every dimension), else none."""
    from ..las import ply_source_from_las

    return replace(model, source=ply_source_from_las(model.source) if ext == ".ply" else None)


_LAS = Format("las", "path", chunk_class="LasChunks", probe=probe, convert=convert, lidar=True)
FORMATS = {".las": _LAS, ".laz": _LAS}
