"""Chunked reading and writing for the streaming and Dask paths: the interface every streamable
format's reader implements (the format table's ``chunks`` entry builds it for a path).

A :class:`ChunkFile` reads points [start, stop) as a chunk :class:`PointModel` (the same
recognition as a whole-file load, applied to the chunk's rows) and serialises a deformed chunk
model back to the records the output holds. Reads use explicit file reads into fresh buffers
(not a memory map), so resident memory stays bounded by the chunk size.

:func:`map_chunks` is the one chunk loop of ``convert``, ``apply`` and a streamed ``deform``:
read a range, turn it into output records, write them through :class:`ChunkWriter` into a
temporary file renamed over the output at the end (:func:`splatdeform.io.atomic.atomic_path`).
A :class:`ChunkFile` is a context manager: leaving it closes what its reader keeps open.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from ..model import PointModel

#: (start, stop) -> (output records, PLY vertex properties or None) of points [start, stop)
ChunkFn = Callable[[int, int], tuple[np.ndarray, "list | None"]]


def chunk_ranges(n: int, chunk: int) -> Iterator[tuple[int, int]]:
    """[start, stop) ranges of at most ``chunk`` points covering ``n`` points."""
    for start in range(0, n, max(1, int(chunk))):
        yield start, min(start + int(chunk), n)


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

    #: {(start, stop): Future of read(start, stop)}: :func:`map_chunks`'s read-ahead
    _ahead: dict | None = None

    def read(self, start: int, stop: int) -> PointModel:
        """Points [start, stop) as a model (every property); the read-ahead's model when
        :func:`map_chunks` already read this range in its reader thread."""
        ahead = self._ahead.pop((start, stop), None) if self._ahead else None
        if ahead is not None:
            return ahead.result()
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
        the input's header and other elements kept; ``props``: :meth:`encode`'s properties.
        A format that can write more records than it reads (PLY: split splats) also takes
        ``extra``, the records written beyond ``n_points`` (its header counts them)."""
        raise NotImplementedError

    def close(self) -> None:
        """Close what the reader keeps open between reads (nothing by default; reopened when
        read again)."""

    def __enter__(self) -> ChunkFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ChunkWriter:
    """Writes chunks' records into ``tmp`` in ``src``'s format (PLY: header, rows, other
    elements verbatim; LAS/LAZ: the input's header, VLRs and EVLRs), opened at the first chunk
    (which gives the output properties); a file of no points gets the header alone. ``extra``:
    records written after the input's ``n_points`` (split splats' children; PLY only), counted
    in the header written first."""

    def __init__(self, src: ChunkFile, tmp: Path, extra: int = 0) -> None:
        self.src, self.tmp, self.extra = src, tmp, int(extra)
        self.out = None

    def write(self, rows: np.ndarray, props: list | None) -> None:
        if self.out is None:
            self.out = self.src.writer(self.tmp, props, extra=self.extra) if self.extra \
                else self.src.writer(self.tmp, props)
        self.out.write(rows)

    def close(self) -> None:
        if self.out is None:   # no points: the header (and other elements) alone
            _, props = self.src.encode(self.src.read(0, 0))
            self.out = self.src.writer(self.tmp, props)
        self.out.close()


def map_chunks(src: ChunkFile, dst: str | Path, fn: ChunkFn, chunk: int, *,
               progress: Callable[[int], None] | None = None,
               before_rename: Callable[[], None] | None = None,
               read_ahead: bool = False, extra: int = 0,
               appendix: Callable[[], Iterable[np.ndarray]] | None = None) -> Path:
    """The one chunk loop: ``fn(start, stop)`` for every range of ``chunk`` points of ``src``,
    its records written in ``src``'s format to ``dst`` atomically (a temporary file beside it,
    renamed at the end; removed on any error). ``progress(n)``: told after each chunk;
    ``before_rename``: a last check that may still refuse (nothing is replaced then).
    ``src`` is closed at the end. Returns ``dst``. ``extra`` and ``appendix``: ``extra`` more
    records (split splats' children, PLY only), written after the chunks' from the record
    arrays ``appendix()`` yields (the header, written first, counts them; a count that does
    not match is an error and nothing is written).

    Reading and writing overlap the computing: the records go to the file from a writer
    thread (in order; one chunk's records in flight), and with ``read_ahead`` (for an ``fn``
    that reads its own range through ``src.read(start, stop)`` and nothing else from ``src``)
    a reader thread reads the next range's model while ``fn`` works on this one. Either way
    one more chunk is held than the loop alone would; the threads are waited for before
    ``src`` closes or the output is renamed or removed."""
    from concurrent.futures import ThreadPoolExecutor

    from splatdeform.interrupts import deferred_signals

    from .atomic import atomic_path

    dst = Path(dst)
    ranges = list(chunk_ranges(src.n_points, chunk))
    reader = ThreadPoolExecutor(1, "splatdeform-read") if read_ahead and len(ranges) > 1 \
        else None
    with src, atomic_path(dst) as tmp:
        writer = ChunkWriter(src, tmp, extra)
        pending = None   # the writer thread's last write
        out = ThreadPoolExecutor(1, "splatdeform-write")
        try:
            if reader is not None:
                src._ahead = {}

                def ahead(i: int) -> None:
                    if i < len(ranges):
                        src._ahead[ranges[i]] = reader.submit(
                            lambda a, b: src.model_of(src.rows(a, b)), *ranges[i])
                ahead(0)
            for i, (start, stop) in enumerate(ranges):
                if reader is not None:
                    ahead(i + 1)
                records = fn(start, stop)
                if pending is not None:
                    pending.result()
                pending = out.submit(writer.write, *records)
                if progress is not None:
                    progress(stop - start)
            if pending is not None:
                pending.result()
            for block in appendix() if appendix is not None else ():
                writer.write(block, None)
        finally:
            # a Ctrl-C or SIGTERM waits until both threads are done: cut short, the wait
            # would let the writer create the temporary file after its removal
            with deferred_signals():
                out.shutdown(wait=True)
                if reader is not None:
                    reader.shutdown(wait=True, cancel_futures=True)
                    src._ahead = None
        if before_rename is not None:
            before_rename()
        writer.close()
    return dst
