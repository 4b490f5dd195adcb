"""Chunked reading and writing for the streaming and Dask paths: the interface every streamable
format's reader implements (the format table's ``chunks`` entry builds it for a path).

A :class:`ChunkFile` reads points [start, stop) as a chunk :class:`PointModel` (the same
recognition as a whole-file load, applied to the chunk's rows) and serialises a deformed chunk
model back to the records the output holds. Reads use explicit file reads into fresh buffers
(not a memory map), so resident memory stays bounded by the chunk size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..model import PointModel


class ChunkFile:
    """``n_points``, ``record_bytes`` (bytes of one raw record), ``positions(start, stop)``,
    ``read(start, stop)`` -> chunk model, ``encode`` and ``writer`` for the output."""

    path: Path
    n_points: int
    record_bytes: int

    def positions(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, 3) float64 coordinates of points [start, stop)."""
        raise NotImplementedError

    def rows(self, start: int, stop: int) -> np.ndarray:
        """The raw records of points [start, stop) (structured array)."""
        raise NotImplementedError

    def read(self, start: int, stop: int) -> PointModel:
        """Points [start, stop) as a model (every property)."""
        return self.model_of(self.rows(start, stop))

    def nonfinite(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows),) bool: the records a ``drop_nonfinite`` load would drop (none where the
        format cannot hold a non-finite value, e.g. LAS's integer coordinates)."""
        return np.zeros(len(rows), dtype=bool)

    def model_of(self, rows: np.ndarray) -> PointModel:
        """A model of raw records (any subset of the file's, e.g. a sample)."""
        raise NotImplementedError

    def encode(self, model: PointModel) -> tuple[np.ndarray, list | None]:
        """(output records (structured array), the PLY vertex properties or None) for a
        deformed chunk model."""
        raise NotImplementedError

    def writer(self, out: Path, props: list | None):
        """An open writer of ``out`` in this file's format (``write(records)``, ``close()``),
        the input's header and other elements kept; ``props``: :meth:`encode`'s properties."""
        raise NotImplementedError
