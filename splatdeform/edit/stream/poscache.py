"""Positions decoded once (issue 45 item 3: each pass done once): a streamed edit reads the
positions of every point in passes 1 to 4 (bounding box, regions, border voxels, border
points); for a compressed source (LAZ) each of those reads decodes the whole file again, at
2-4 M points/s on this machine. :class:`PositionCache` keeps the float64 positions that pass 1
decoded in an unnamed temporary file beside the output (24 bytes a point, on disk, not in
memory: it is read back chunk by chunk) and serves the later passes from it, bit for bit the
same arrays. Pass 5 still reads the records themselves (it writes every field)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from splatdeform.io.chunks import ChunkFile

_ROW = 3 * 8   # bytes of one point's x, y, z float64


class PositionCache:
    """A view of ``src`` whose ``positions(start, stop)`` of chunks already decoded come from
    the cache file; the first sequential pass over the file fills it. Every other attribute
    is ``src``'s. Close it (or use it as a context manager) to free the file."""

    def __init__(self, src: ChunkFile, folder: Path) -> None:
        self._src = src
        self._file = tempfile.TemporaryFile(prefix=".splatdeform-positions-", dir=folder)
        self._filled = 0   # the first points whose positions are in the cache

    def __getattr__(self, name: str):
        return getattr(self._src, name)

    def positions(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, 3) float64 positions of points [start, stop)."""
        stop = min(stop, self._src.n_points)
        if stop <= self._filled:
            self._file.seek(start * _ROW)
            out = np.fromfile(self._file, dtype="<f8", count=(stop - start) * 3)
            return out.reshape(-1, 3)
        pos = self._src.positions(start, stop)
        if start == self._filled:   # the next chunk of the first pass: keep it
            self._file.seek(start * _ROW)
            np.ascontiguousarray(pos, dtype="<f8").tofile(self._file)
            self._filled = stop
        return pos

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> PositionCache:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def cached_positions(src: ChunkFile, out: Path) -> PositionCache | None:
    """A :class:`PositionCache` of ``src`` beside ``out`` when its positions are costly to
    read again (a compressed LAZ), else None (a binary PLY or LAS reads them at disk speed)."""
    if not getattr(src, "compressed", False):
        return None
    folder = Path(out).parent   # the output's disk (a tmpfs /tmp would hold it in memory)
    return PositionCache(src, folder if folder.is_dir() else Path(src.path).parent)
