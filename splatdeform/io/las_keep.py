"""A LAS/LAZ file's own header, VLR and EVLR bytes, kept through a save.

laspy rewrites what it writes: it parses known VLRs and serialises them again (a
GeoKeyDirectory whose key count it "corrects", Extra Bytes descriptions with their statistics
reset), zeroes a LAS 1.4 file's legacy point counts, recomputes points-by-return from
``return_number`` (all zero when a point format 6-10 file leaves it unset) and stamps today's
creation date. :func:`read_raw` keeps the input's bytes; :func:`writable_vlrs` hands laspy the
VLRs as opaque records of the same length (so the layout it writes matches the input's), and
:func:`restore` puts the input's bytes back after the write.

What a save keeps and what it changes (docs/guides/lidar.md):

- kept verbatim: every header byte (file source id, global encoding, GUID, version, system and
  software identifiers, creation date, extra header bytes) except the fields below, and every
  VLR and EVLR (its 54/60-byte record header and payload);
- point counts and points-by-return (legacy and 64-bit): the input's when the number of points
  is the same; otherwise counted from ``return_number`` (1..15; when no point sets it and the
  input counted every point as a first return, every point is counted so again), and the
  legacy fields filled only where the input filled them;
- COPC (a LAZ 1.4 whose ``copc`` VLRs and hierarchy EVLR describe an octree of its point
  chunks): read as the LAZ it is; written as plain LAZ 1.4 (or LAS) without the ``copc``
  records, whose octree the rewritten chunks no longer follow (a warning says so);
- changed as they must: the bounding box (from the written coordinates), scale and offset when
  deformed coordinates need them moved, the offset to the points, the VLR count and the LAZ
  bit of the point format byte when the output's compression differs from the input's (the
  ``laszip encoded`` VLR is the writer's own), and the EVLR start.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

from .las_header import EVLR_HEAD, HEADER_SIZES, LASZIP_RECORD, LASZIP_USER, VLR_HEAD
from .regular import open_regular

MAX_KEPT_EVLR_BYTES = 256 << 20   # EVLRs larger than this (waveforms) are left to laspy
_COUNTS = slice(107, 131)         # legacy point count + 5 legacy points-by-return
_COUNTS_14 = slice(247, 375)      # LAS 1.4: 64-bit point count + 15 points-by-return
_MUST_CHANGE = (slice(94, 107), slice(131, 227), slice(227, 247))  # see the module docstring


@dataclass(frozen=True)
class RawLas:
    """The input's header bytes (its declared header size) and its VLR and EVLR records,
    each whole (record header + payload); ``evlrs`` None when they were not kept."""

    head: bytes
    vlrs: tuple[bytes, ...]
    evlrs: tuple[bytes, ...] | None

    @property
    def copc(self) -> bool:
        """The file is a COPC (Cloud Optimized Point Cloud): it holds the ``copc`` info VLR."""
        return any(_user(r) == COPC_USER for r in self.vlrs)

    @property
    def minor(self) -> int:
        return self.head[25]

    @property
    def point_count(self) -> int:
        if self.minor >= 4:
            return struct.unpack_from("<Q", self.head, 247)[0]
        return struct.unpack_from("<I", self.head, 107)[0]


COPC_USER = b"copc"
COPC_NOTE = ("written as plain LAZ 1.4: the COPC octree (its copc VLRs and hierarchy) is not "
             "kept")


def _user(record: bytes) -> bytes:
    return record[2:18].split(b"\0", 1)[0]


def _is_laszip(record: bytes) -> bool:
    return _user(record) == LASZIP_USER and struct.unpack_from("<H", record, 18)[0] == \
        LASZIP_RECORD


def _kept(records) -> list[bytes]:
    """The records a save writes back: all but the LAZ one (the writer's own) and COPC's."""
    return [r for r in records if not _is_laszip(r) and _user(r) != COPC_USER]


def _records(f, start: int, count: int, end: int, head: int, long: bool) -> list[bytes]:
    """``count`` whole records from ``start`` (bounds already checked by check_header)."""
    out = []
    at = start
    for _ in range(count):
        f.seek(at)
        raw = f.read(head)
        if len(raw) < head:
            break
        length = struct.unpack_from("<Q" if long else "<H", raw, 20)[0]
        if at + head + length > end:
            break
        out.append(raw + f.read(length))
        at += head + length
    return out


def read_raw(path: str | Path) -> RawLas:
    """The header, VLR and EVLR bytes of a LAS/LAZ file that
    :func:`~splatdeform.io.las_header.check_header` accepted."""
    with open_regular(path) as f:
        size = f.seek(0, 2)
        f.seek(0)
        fixed = f.read(375)
        header_size, offset, n_vlrs = struct.unpack_from("<HII", fixed, 94)
        f.seek(0)
        head = f.read(header_size)
        vlrs = _records(f, header_size, n_vlrs, offset, VLR_HEAD, False)
        evlrs: list[bytes] | None = []
        if head[25] >= 4 and len(head) >= 247:
            start, count = struct.unpack_from("<QI", head, 235)
            if count and size - start <= MAX_KEPT_EVLR_BYTES:
                evlrs = _records(f, start, count, size, EVLR_HEAD, True)
            elif count:
                evlrs = None
    return RawLas(head, tuple(vlrs), None if evlrs is None else tuple(evlrs))


def _opaque(record: bytes, head: int):
    """A laspy VLR holding ``record``'s payload as opaque bytes (written back unparsed)."""
    import laspy

    def text(raw: bytes) -> str:
        return raw.split(b"\0", 1)[0].decode("ascii", "replace").replace("\ufffd", "?")

    return laspy.VLR(text(record[2:18]), struct.unpack_from("<H", record, 18)[0],
                     text(record[head - 32:head]), bytes(record[head:]))


def writable_vlrs(raw: RawLas) -> list:
    """The input's VLRs (the LAZ one left out: the writer makes its own) as opaque laspy VLRs:
    laspy writes their payloads unchanged, so every record keeps its length and place."""
    return [_opaque(r, VLR_HEAD) for r in _kept(raw.vlrs)]


def writable_evlrs(raw: RawLas) -> list | None:
    """The input's EVLRs as opaque laspy VLRs (None when they were not kept)."""
    if raw.evlrs is None:
        return None
    return [_opaque(r, EVLR_HEAD) for r in _kept(raw.evlrs)]


def _counted(head: bytearray, written: bytes, raw: RawLas) -> None:
    """Fill the count fields of ``head`` (the input's bytes) for a written file whose point
    count differs from the input's: laspy's counts from ``return_number``, with the input's
    conventions (see the module docstring)."""
    minor = raw.minor
    if minor >= 4:
        n = struct.unpack_from("<Q", written, 247)[0]
        by_return = list(struct.unpack_from("<15Q", written, 255))
        old_by = struct.unpack_from("<15Q", raw.head, 255)
    else:
        n = struct.unpack_from("<I", written, 107)[0]
        by_return = list(struct.unpack_from("<5I", written, 111)) + [0] * 10
        old_by = struct.unpack_from("<5I", raw.head, 111)
    if n and not any(by_return) and old_by[0] == raw.point_count and raw.point_count:
        by_return[0] = n     # the input counted its unset return numbers as first returns
    if minor >= 4:
        struct.pack_into("<Q15Q", head, 247, n, *by_return)
        old_legacy, *old_legacy_by = struct.unpack_from("<I5I", raw.head, 107)
        fits = n <= 0xFFFFFFFF and max(by_return[:5]) <= 0xFFFFFFFF
        legacy = n if old_legacy and fits else 0
        legacy_by = by_return[:5] if any(old_legacy_by) and fits and not any(by_return[5:]) \
            else [0] * 5
        struct.pack_into("<I5I", head, 107, legacy, *legacy_by)
    else:
        struct.pack_into("<I5I", head, 107, n, *by_return[:5])


def _walk(data: bytes, start: int, count: int, head: int, long: bool) -> list[tuple[int, int]]:
    """(position, length) of ``count`` records from ``start`` in ``data``."""
    out, at = [], start
    for _ in range(count):
        if at + head > len(data):
            break
        length = struct.unpack_from("<Q" if long else "<H", data, at + 20)[0]
        out.append((at, head + length))
        at += head + length
    return out


def _put_records(f, data: bytes, places: list[tuple[int, int]], kept: list[bytes],
                 base: int) -> None:
    """Write each kept record over the written one at the same place when they agree in
    record id and length (a differing record, e.g. the writer's LAZ VLR, stays the writer's)."""
    for (at, length), record in zip(places, kept, strict=False):
        mine = data[at - base:at - base + length]
        if len(record) == length and mine[18:20] == record[18:20] and mine != record:
            f.seek(at)
            f.write(record)


def restore(out: str | Path, raw: RawLas) -> None:
    """Put ``raw``'s header fields, VLR and EVLR bytes back into the file laspy wrote at
    ``out`` (the fields that must change are the written ones; see the module docstring)."""
    with open(out, "r+b") as f:
        fixed = f.read(375)
        header_size, offset, n_vlrs = struct.unpack_from("<HII", fixed, 94)
        minor = fixed[25]
        f.seek(0)
        written = f.read(offset)
        std = HEADER_SIZES.get(minor, 227)
        head = bytearray(raw.head[:header_size].ljust(header_size, b"\0"))
        if len(raw.head) != header_size or raw.head[24:26] != written[24:26]:
            head = bytearray(written[:header_size])   # another layout: counts only
        for part in _MUST_CHANGE:
            stop = min(part.stop, std)
            if part.start < stop:
                head[part.start:stop] = written[part.start:stop]
        same_count = raw.point_count == (struct.unpack_from("<Q", written, 247)[0]
                                         if minor >= 4 else
                                         struct.unpack_from("<I", written, 107)[0])
        if same_count:
            head[_COUNTS] = raw.head[_COUNTS]
            if minor >= 4:
                head[_COUNTS_14] = raw.head[_COUNTS_14]
        else:
            _counted(head, written, raw)
        f.seek(0)
        f.write(bytes(head))
        kept_vlrs = _kept(raw.vlrs)
        places = [p for p in _walk(written, header_size, n_vlrs, VLR_HEAD, False)
                  if not _is_laszip(written[p[0]:p[0] + VLR_HEAD])]
        _put_records(f, written, places, kept_vlrs, 0)
        if minor >= 4 and raw.evlrs:
            start, count = struct.unpack_from("<QI", head, 235)
            f.seek(start)
            tail = f.read()
            _put_records(f, tail, [(at + start, n) for at, n in
                                   _walk(tail, 0, count, EVLR_HEAD, True)],
                         _kept(raw.evlrs), start)

