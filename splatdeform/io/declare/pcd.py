"""PCD (our own reader/writer, every field kept): the reader's own header parser
(:func:`splatdeform.io.pcd.parse_header`, which checks the declared POINTS / WIDTH x HEIGHT
against the file size for every DATA encoding) is the probe."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from ..format import FileCost, Format

if TYPE_CHECKING:
    from ...model import PointModel

# Measured costs of the PCD reader beside its decoded records: the raw file, and for
# binary_compressed the LZF output buffer and its bytes copy; ascii: the split rows, a bytes
# object per value and the (N, columns) object array of value texts kept for a lossless save.
PCD_ASCII_BYTES_PER_VALUE = 120


def probe(path: Path, head: bytes, size: int, file: Path | None = None) -> FileCost:
    """The points are the header's, whatever the encoding (a binary_compressed body holds more
    points than its size suggests)."""
    from ..pcd import parse_header

    source, _ = parse_header(path, head, size)
    points = source.width * source.height
    item = source.data.dtype.itemsize
    record_bytes = item + 48   # the records, float64 positions (and normals)
    load = size + 2 * points * item + points * 48
    if source.encoding == "binary_compressed":
        load += 2 * points * item   # the LZF output and its bytes copy
    elif source.encoding == "ascii":
        load += 2 * size + points * sum(source.counts) * PCD_ASCII_BYTES_PER_VALUE
    return FileCost(points, size, record_bytes, load)


def fields(path: Path) -> dict:
    """``info``'s PCD fields: the DATA encoding, version, width, height and fields, and for an
    organized cloud its grid and how many cells are finite points ('organized 640x480 with
    182,292 finite')."""
    from .. import pcd

    source, _ = pcd.read_source(path)
    out = {"version": dict(source.header).get("VERSION", "?"), "width": source.width,
           "height": source.height, "fields": " ".join(source.fields)}
    if source.height > 1:
        xyz = pcd.xyz_of(source.data)
        source = pcd.organized_holes(path, source, xyz)
        out["organized"] = source.organized
    return {"format": f"PCD DATA {source.encoding}", "format_fields": out}


def convert(model: PointModel, ext: str) -> PointModel:
    """A PCD-read model written as another format: its source as a PLY's (a PLY output keeps
    every field), else none."""
    from ..pcd import ply_source_from_pcd

    return replace(model, source=ply_source_from_pcd(model.source) if ext == ".ply" else None)


FORMATS = {".pcd": Format("pcd", probe=probe, fields=fields, convert=convert)}
