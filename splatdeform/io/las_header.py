"""Check a LAS/LAZ header against the file before laspy allocates or reads anything.

laspy trusts the header: a VLR count of 2^31 makes it loop for minutes, an EVLR offset or point
count past the end makes it allocate gigabytes, a version it does not know ends in a traceback,
a scale of ``inf`` gives non-finite coordinates, and a changed point format is silently read as
another record layout. :func:`check_header` reads only the fixed header and the record headers
of the VLRs/EVLRs (walking at most as many as the file can hold) and raises one
:class:`FormatError` line naming the file and the field.
"""

from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path

from ..errors import FormatError
from ..model import MAX_COORDINATE
from .regular import open_regular

MIN_HEADER = 227
HEADER_SIZES = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}  # by version minor
VLR_HEAD, EVLR_HEAD = 54, 60
# standard record size of each point format (LAS 1.4 R15 table 7 ff.)
RECORD_SIZES = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}
EXTRA_TYPE_SIZES = [0, 1, 1, 2, 2, 4, 4, 8, 8, 4, 8]  # Extra Bytes data_type 1..10
# LAZ decodes at least this many points per compressed byte at most (generous: constant
# records compress to a few bits each); more declared points than this is a corrupt count
MAX_LAZ_POINTS_PER_BYTE = 64


@dataclass(frozen=True)
class LasLayout:
    """What :func:`check_header` verified: version (major, minor), base point format, record
    length, point count, offset of the point data, compressed (LAZ) and the file size."""

    version: tuple[int, int]
    point_format: int
    record_length: int
    point_count: int
    offset_to_points: int
    compressed: bool
    file_size: int
    laz_chunk_points: int = 0   # LAZ: points per compressed chunk (0: variable or unknown)


LASZIP_USER = b"laszip encoded"
LASZIP_RECORD = 22204
VARIABLE_CHUNKS = 0xFFFFFFFF


def scale_offset_fault(axis: str, scale: float, offset: float) -> str:
    """What is wrong with an axis' scale and offset ('' when nothing): the one rule the reader
    holds a header to and the writer holds itself to (non-zero finite scale, finite offset,
    every int32 coordinate within :data:`~splatdeform.model.MAX_COORDINATE`)."""
    if not (math.isfinite(scale) and scale != 0.0 and math.isfinite(offset)):
        return (f"{axis} scale {scale} / offset {offset}: expected finite numbers and a "
                "non-zero scale")
    if abs(scale) * 2.0**31 + abs(offset) > MAX_COORDINATE:
        return f"{axis} scale {scale} / offset {offset} give coordinates beyond {MAX_COORDINATE:g}"
    return ""


def _fail(path: Path, message: str) -> FormatError:
    return FormatError(f"{path}: corrupt LAS/LAZ header: {message}")


def _extra_bytes_size(payload: bytes) -> int | None:
    """Bytes per point the Extra Bytes VLR describes (None when it cannot be told)."""
    total = 0
    for at in range(0, len(payload) - 191, 192):
        dtype, options = payload[at + 2], payload[at + 3]
        if dtype == 0:
            total += options
        elif 1 <= dtype <= 10:
            total += EXTRA_TYPE_SIZES[dtype]
        elif 11 <= dtype <= 30:  # deprecated 2- and 3-element arrays
            total += EXTRA_TYPE_SIZES[(dtype - 11) % 10 + 1] * (2 if dtype <= 20 else 3)
        else:
            return None
    return total


def _walk(f, path: Path, what: str, start: int, count: int, end: int, head: int,
          long_lengths: bool, available: int | None = None) -> tuple[bytes | None, int | None]:
    """Walk ``count`` variable-length records from ``start`` that must end by ``end``; return
    the payload of an Extra Bytes record (LASF_Spec 4) if there is one, and the LAZ chunk size
    of the laszip record (None when there is none). ``available``: bytes of the file that ``f``
    holds (the first bytes only, e.g. an archive member's head): the walk stops, unchecked,
    where they end."""
    if count > (end - start) // head:
        raise _fail(path, f"{count} {what}s declared but only {end - start} bytes for them "
                          f"(each needs at least {head})")
    at, extra, chunk = start, None, None
    for i in range(count):
        if available is not None and at + head > available:
            break
        f.seek(at)
        raw = f.read(head)
        if len(raw) < head:
            raise _fail(path, f"{what} {i} is truncated")
        user = raw[2:18].split(b"\0", 1)[0]
        record_id = struct.unpack_from("<H", raw, 18)[0]
        length = (struct.unpack_from("<Q", raw, 20)[0] if long_lengths
                  else struct.unpack_from("<H", raw, 20)[0])
        if at + head + length > end:
            raise _fail(path, f"{what} {i} declares {length} bytes of data, past the end of its "
                              f"area (byte {end})")
        if user == b"LASF_Spec" and record_id == 4 and length <= 192 * 4096:
            extra = f.read(length)
        elif user == LASZIP_USER and record_id == LASZIP_RECORD and length >= 16:
            laszip = f.read(16)
            if len(laszip) == 16:
                chunk = struct.unpack_from("<I", laszip, 12)[0]
        at += head + length
    return extra, chunk


def check_header(path: str | Path) -> LasLayout:
    """Validate the header of the LAS/LAZ file at ``path`` against its size (raises
    FormatError naming the file and the field). The file is opened with the one opener
    (:func:`splatdeform.io.regular.open_regular`: a FIFO or device is refused, not read)."""
    path = Path(path)
    with open_regular(path) as f:
        return check_header_in(f, path, os.fstat(f.fileno()).st_size)


def check_header_bytes(name: str | Path, head: bytes, size: int) -> LasLayout:
    """:func:`check_header` from the file's first bytes ``head`` and its ``size`` (an archive
    member judged before it is extracted): the same checks, except that VLRs beyond ``head``
    are not walked (their count and area are still checked against the size)."""
    import io

    return check_header_in(io.BytesIO(head), Path(name), size, available=len(head))


def check_header_in(f, path: Path, size: int, available: int | None = None) -> LasLayout:
    """:func:`check_header` on an open binary file ``f`` of ``size`` bytes (``available``: how
    many of them ``f`` holds, None: all)."""
    raw = f.read(375)
    if raw[:4] != b"LASF":
        raise FormatError(f"{path}: not a LAS/LAZ file (it does not start with 'LASF')")
    if len(raw) < MIN_HEADER:
        raise _fail(path, f"the file has {size} bytes, less than the {MIN_HEADER}-byte "
                          "header")
    major, minor = raw[24], raw[25]
    if major != 1 or minor not in HEADER_SIZES:
        raise _fail(path, f"version {major}.{minor} is not supported (expected 1.0 to 1.4)")
    header_size, offset, n_vlrs = struct.unpack_from("<HII", raw, 94)
    fmt_byte, record_length, legacy_count = struct.unpack_from("<BHI", raw, 104)
    scales = struct.unpack_from("<3d", raw, 131)
    offsets = struct.unpack_from("<3d", raw, 155)
    need = HEADER_SIZES[minor]
    if header_size < need or header_size > size:
        raise _fail(path, f"header size {header_size} (expected {need} for LAS 1.{minor}, "
                          f"within the {size}-byte file)")
    if len(raw) < need:
        raise _fail(path, f"the file has {size} bytes, less than the {need}-byte header")
    if not header_size <= offset <= size:
        raise _fail(path, f"offset to point data {offset} is outside the file "
                          f"({header_size}..{size})")
    compressed = bool(fmt_byte & 0xC0)
    fmt = fmt_byte & 0x3F
    if fmt not in RECORD_SIZES or (fmt > 5 and minor < 4):
        raise _fail(path, f"point format {fmt} is not valid for LAS 1.{minor}")
    if record_length < RECORD_SIZES[fmt]:
        raise _fail(path, f"point record length {record_length} is shorter than point "
                          f"format {fmt} needs ({RECORD_SIZES[fmt]})")
    for axis, s, o in zip("xyz", scales, offsets, strict=True):
        fault = scale_offset_fault(axis, s, o)
        if fault:
            raise _fail(path, fault)
    count = legacy_count
    evlr_start, n_evlrs = 0, 0
    if minor >= 4:
        evlr_start, n_evlrs, count = struct.unpack_from("<QIQ", raw, 235)
        if legacy_count and legacy_count != count:
            raise _fail(path, f"legacy point count {legacy_count} differs from the point "
                              f"count {count}")
    points_end = size
    if n_evlrs:
        if not offset <= evlr_start <= size - EVLR_HEAD:
            raise _fail(path, f"{n_evlrs} EVLRs declared at byte {evlr_start}, outside the "
                              f"file ({offset}..{size})")
        points_end = evlr_start
    if compressed:
        if count > (points_end - offset) * MAX_LAZ_POINTS_PER_BYTE:
            raise _fail(path, f"{count} points declared in {points_end - offset} bytes of "
                              "compressed point data")
    elif offset + count * record_length > points_end:
        raise _fail(path, f"{count} points of {record_length} bytes declared but the point "
                          f"data has {points_end - offset} bytes")
    extra, chunk = _walk(f, path, "VLR", header_size, n_vlrs, offset, VLR_HEAD, False,
                         available)
    if n_evlrs:
        more, evlr_chunk = _walk(f, path, "EVLR", evlr_start, n_evlrs, size, EVLR_HEAD,
                                 True, available)
        extra, chunk = more or extra, chunk or evlr_chunk
    walked = available is None or (offset <= available and (not n_evlrs or size <= available))
    if walked or extra is not None:
        _check_extra_bytes(path, fmt, record_length, extra)
    laz_chunk = 0 if not compressed or chunk in (None, 0, VARIABLE_CHUNKS) else int(chunk)
    return LasLayout((major, minor), fmt, record_length, count, offset, compressed, size,
                     laz_chunk)


def _check_extra_bytes(path: Path, fmt: int, record_length: int, extra: bytes | None) -> None:
    """A record longer than its format is only valid with the extra bytes described: else the
    point format byte was most likely changed and the records would be misread."""
    surplus = record_length - RECORD_SIZES[fmt]
    if surplus == 0:
        return
    described = None if extra is None else _extra_bytes_size(extra)
    if described is None or described != surplus:
        said = "no Extra Bytes VLR" if extra is None else f"{described} described"
        raise _fail(path, f"point record length {record_length} is point format {fmt} "
                          f"({RECORD_SIZES[fmt]} bytes) plus {surplus} extra bytes, but the "
                          f"file has {said}; the point format field does not match the records")
