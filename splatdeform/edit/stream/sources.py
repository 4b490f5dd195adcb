"""Chunked readers and writers for the streaming and Dask paths: binary PLY and LAS/LAZ.

A :class:`ChunkFile` reads points [start, stop) as a chunk :class:`PointModel` (the same
recognition as a whole-file load, applied to the chunk's rows) and serialises a deformed chunk
model back to the bytes/records the output holds. Reads use explicit file reads into fresh
buffers (not a memory map), so resident memory stays bounded by the chunk size.

Streamable: binary PLY (either byte order) whose ``vertex`` element is the first element and
holds scalar properties only, and that has no faces (``face``/``tristrips`` with rows); any
other element after the vertices is copied verbatim. LAS/LAZ (every point format).
"""

from __future__ import annotations

import os
from dataclasses import fields
from pathlib import Path

import numpy as np

from splatdeform.errors import FormatError, InputError
from splatdeform.io import STREAMABLE, extension_of
from splatdeform.io import las as laslib
from splatdeform.io import ply as plylib
from splatdeform.io import ply_format as plyfmt
from splatdeform.model import MAX_COORDINATE, PlyElementData, PlySource, PointModel

__all__ = ["STREAMABLE", "open_chunks"]  # STREAMABLE: the io format table's streamable list


class ChunkModel(PointModel):
    """A chunk of a bigger model: region selectors see the whole file's bounding box."""

    lo: np.ndarray
    hi: np.ndarray

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        return self.lo, self.hi


def as_chunk(model: PointModel, lo: np.ndarray, hi: np.ndarray) -> ChunkModel:
    """``model`` (no copy) as a ChunkModel whose bbox() is (lo, hi) (3,) each."""
    chunk = ChunkModel(**{f.name: getattr(model, f.name) for f in fields(PointModel)})
    chunk.lo, chunk.hi = lo, hi
    return chunk


class ChunkFile:
    """Base: ``n_points``, ``positions(start, stop)``, ``read(start, stop)`` -> chunk model."""

    path: Path
    n_points: int

    def positions(self, start: int, stop: int) -> np.ndarray:
        raise NotImplementedError

    def read(self, start: int, stop: int) -> PointModel:
        raise NotImplementedError

    def encode(self, model: PointModel) -> np.ndarray:
        """The output rows (structured array) for a deformed chunk model."""
        raise NotImplementedError

    def rows(self, start: int, stop: int) -> np.ndarray:
        """The raw records of points [start, stop) (structured array)."""
        raise NotImplementedError

    def model_of(self, rows: np.ndarray) -> PointModel:
        """A model of raw records (any subset of the file's, e.g. a sample)."""
        raise NotImplementedError


class PlyChunks(ChunkFile):
    """Binary PLY, vertex element first, scalar properties only."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        with open(self.path, "rb") as f:
            head = f.read(plyfmt.MAX_HEADER_BYTES)
        header = plyfmt.parse_header(self.path, head)
        if header.text:
            raise InputError(f"{self.path}: streaming needs a binary PLY (this one is ascii); "
                             "raise --memory-budget or convert it to binary")
        if not header.elements or header.elements[0][0] != "vertex":
            raise InputError(f"{self.path}: streaming needs the 'vertex' element first")
        name, count, props = header.elements[0]
        if any(p.is_list for p in props):
            raise InputError(f"{self.path}: streaming needs scalar vertex properties")
        for el_name, el_count, _ in header.elements[1:]:
            if el_name in ("face", "tristrips") and el_count > 0:
                raise InputError(f"{self.path}: streaming handles point clouds; this is a mesh "
                                 f"({el_count} {el_name} rows): raise --memory-budget")
        self.header = header
        self.props = props
        self.n_points = count
        self.byte_order = header.byte_order
        self.dtype = np.dtype([(p.name, self.byte_order + p.dtype) for p in props])
        self.data_offset = header.size
        self.tail_offset = header.size + count * self.dtype.itemsize
        size = os.path.getsize(self.path)
        if size < self.tail_offset:
            raise FormatError(f"{self.path}: truncated binary body: {size} bytes, the vertex "
                              f"element needs {self.tail_offset}")
        missing = [a for a in "xyz" if a not in self.dtype.names]
        if missing:
            raise FormatError(f"{self.path}: vertex element lacks property {', '.join(missing)}")

    def _rows(self, start: int, stop: int, names: tuple[str, ...] | None = None) -> np.ndarray:
        with open(self.path, "rb") as f:
            f.seek(self.data_offset + start * self.dtype.itemsize)
            rows = np.fromfile(f, dtype=self.dtype, count=stop - start)
        if rows.shape[0] != stop - start:
            raise FormatError(f"{self.path}: truncated binary body at vertex {start}")
        return rows

    def positions(self, start: int, stop: int) -> np.ndarray:
        rows = self._rows(start, stop)
        out = np.empty((stop - start, 3), dtype=np.float64)
        for i, a in enumerate("xyz"):
            out[:, i] = rows[a]
        if not np.isfinite(out).all():
            bad = int(np.flatnonzero(~np.isfinite(out).all(axis=1))[0]) + start
            raise FormatError(f"{self.path}: vertex {bad} has NaN/Inf coordinates (streaming "
                              "cannot drop them; fix the file)")
        far = np.abs(out).max(axis=1) > MAX_COORDINATE if out.size else None
        if far is not None and far.any():
            bad = int(np.flatnonzero(far)[0]) + start
            raise FormatError(f"{self.path}: point {bad} at {out[bad - start].tolist()} is beyond "
                              f"+-{MAX_COORDINATE:g}; the fit would overflow; fix or crop the "
                              "file")
        return out

    def rows(self, start: int, stop: int) -> np.ndarray:
        return self._rows(start, stop)

    def read(self, start: int, stop: int) -> PointModel:
        return self.model_of(self._rows(start, stop))

    def model_of(self, rows: np.ndarray) -> PointModel:
        source = PlySource([PlyElementData("vertex", self.props, rows)],
                           self.header.comments, self.header.obj_info, False, self.byte_order)
        return plylib.model_from_source(source, self.path)

    def encode(self, model: PointModel) -> np.ndarray:
        vertex = plylib.source_for_save(model).element("vertex")
        dtype = np.dtype([(p.name, self.byte_order + p.dtype) for p in vertex.properties])
        return vertex.data.astype(dtype, copy=False), vertex.properties

    def header_bytes(self, props) -> bytes:
        elements = [PlyElementData("vertex", props, np.empty(self.n_points, dtype=[]))]
        elements += [PlyElementData(n, p, np.empty(c, dtype=[]))
                     for n, c, p in self.header.elements[1:]]
        source = PlySource(elements, self.header.comments, self.header.obj_info, False,
                           self.byte_order)
        return plyfmt._header_text(source, False, self.byte_order)

    def copy_tail(self, out) -> None:
        """Copy the bytes after the vertex element (other elements) verbatim."""
        with open(self.path, "rb") as f:
            f.seek(self.tail_offset)
            while True:
                block = f.read(1 << 24)
                if not block:
                    break
                out.write(block)


class LasChunks(ChunkFile):
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.header, self.compressed, self.evlrs = laslib.read_header(self.path)
        self.n_points = int(self.header.point_count)
        self.scales = np.asarray(self.header.scales, dtype=np.float64)
        self.offsets = np.asarray(self.header.offsets, dtype=np.float64)

    def _records(self, start: int, stop: int) -> np.ndarray:
        parts = list(laslib.iter_chunks(self.path, stop - start, start, stop))
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def positions(self, start: int, stop: int) -> np.ndarray:
        return laslib.positions_of(self.header, self._records(start, stop))

    def rows(self, start: int, stop: int) -> np.ndarray:
        return self._records(start, stop)

    def read(self, start: int, stop: int) -> PointModel:
        return self.model_of(self._records(start, stop))

    def model_of(self, rows: np.ndarray) -> PointModel:
        return laslib.model_from_las(self.header, rows, self.path, compressed=self.compressed)

    def encode(self, model: PointModel) -> np.ndarray:
        src = model.source
        ints = laslib.quantize(model.positions, laslib.positions_of(self.header, src.points),
                               laslib._original_xyz(src.points), self.scales, self.offsets,
                               np.zeros(3, dtype=np.int64), True)
        points = src.points.copy()
        for i, axis in enumerate("XYZ"):
            points[axis] = ints[:, i]
        names = points.dtype.names or ()
        if model.normals is not None and all(n in names for n in laslib.NORMAL_NAMES):
            for i, n in enumerate(laslib.NORMAL_NAMES):
                points[n] = model.normals[:, i].astype(points.dtype[n])
        return points, None


def open_chunks(path: str | Path) -> ChunkFile:
    """The chunk reader for ``path`` by extension (InputError when not streamable)."""
    path = Path(path)
    ext = extension_of(path)
    if ext in STREAMABLE and ext in laslib.EXTENSIONS:
        return LasChunks(path)
    if ext in STREAMABLE:
        return PlyChunks(path)
    raise InputError(f"{path}: streaming reads {', '.join(STREAMABLE)} (PLY binary); this "
                     f"{ext or 'extensionless'} file must fit the memory budget (raise "
                     "--memory-budget)")
