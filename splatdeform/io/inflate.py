"""Bounded decompression: a gzip/zlib/deflate stream or a ZIP member is inflated a chunk at a
time with a maximum output (what its header declares), and refused with one line naming the file
as soon as the output would pass that maximum or the stream ends short of it.

A declared size is also checked before anything is inflated:

- against the compressed size: deflate cannot expand a stream by more than ~1032x (a 258-byte
  match in under 2 bits), so a header declaring more than :data:`MAX_RATIO` x its compressed
  bytes (+ :data:`RATIO_SLACK`) lies;
- against the machine's memory (:func:`memory_cap`): a declared size whose decoded arrays could
  not fit is refused before inflating.

- :class:`Inflater`: a stream read with bounded output (``read``, ``readinto``, ``expect_end``).
- :func:`inflate_gzip`: the whole of a gzip stream, at most ``max_out`` bytes (``exact``: exactly).
- :func:`inflate_zip_member`: one member of an open ZIP archive, at most ``max_out`` bytes.
- :func:`gzip_isize`: the uncompressed size (mod 2^32) a one-member gzip stream's trailer states.
"""

from __future__ import annotations

import os
import struct
import zipfile
import zlib
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ..errors import FormatError

#: deflate's largest expansion: 258 bytes out per (a little under) 2 bits in ~ 1032:1
MAX_RATIO = 1032
#: headers, trailers and tiny streams on top of the ratio
RATIO_SLACK = 1 << 16
#: output bytes per step of a bounded read
CHUNK = 1 << 20
#: compressed bytes read from a file per step
IN_CHUNK = 1 << 16
#: gzip framing (wbits for zlib.decompressobj)
GZIP = 31
ZLIB = 15
RAW = -15
_GZIP_MAGIC = b"\x1f\x8b"

Source = bytes | bytearray | memoryview | BinaryIO


def memory_cap() -> int:
    """The machine's physical memory in bytes: decoded arrays that a header declares larger
    than this cannot be held, and are refused before anything is inflated."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not Linux
        return 8 << 30


def max_inflated(compressed: int) -> int:
    """The most bytes a deflate stream of ``compressed`` bytes can inflate to."""
    return MAX_RATIO * max(int(compressed), 0) + RATIO_SLACK


def check_declared(path: str | Path, what: str, declared: int, compressed: int | None = None,
                   *, decoded: int | None = None) -> None:
    """Refuse a header's ``declared`` uncompressed size before inflating: more than the
    ``compressed`` bytes can hold (:func:`max_inflated`), or ``decoded`` (the bytes of the arrays
    it would decode to; default ``declared``) more than :func:`memory_cap`."""
    if compressed is not None and declared > max_inflated(compressed):
        raise FormatError(f"{path}: {what} declares {declared:,} bytes uncompressed, more than "
                          f"its {compressed:,} compressed bytes can hold (deflate expands at "
                          f"most {MAX_RATIO}x)")
    need = declared if decoded is None else decoded
    cap = memory_cap()
    if need > cap:
        raise FormatError(f"{path}: {what} declares data that decodes to {need:,} bytes, more "
                          f"than this machine's {cap:,} bytes of memory")


def gzip_isize(data: bytes | bytearray | memoryview) -> int | None:
    """The ISIZE field (uncompressed size mod 2^32) of a gzip stream's trailer, None when the
    data is too short to have one. Only the last member's size for a multi-member stream."""
    if len(data) < 18:
        return None
    return struct.unpack("<I", bytes(data[-4:]))[0]


class Inflater:
    """A gzip (default), zlib or raw deflate stream read with bounded output: each call inflates
    at most what it was asked for (``zlib``'s ``max_length``), so a bomb never grows past the
    caller's buffer. ``source``: the compressed bytes, or a binary file read ``IN_CHUNK`` at a
    time. A gzip stream may hold several members (as Python's gzip reads them); anything else
    after the stream is refused. Errors: FormatError naming ``path`` and ``what``."""

    def __init__(self, source: Source, path: str | Path, what: str, *,
                 wbits: int = GZIP) -> None:
        self.path, self.what, self.wbits = path, what, wbits
        self._file = None if isinstance(source, bytes | bytearray | memoryview) else source
        self._data = None if self._file is not None else memoryview(source).cast("B")
        self._at = 0
        self._pending = b""
        self._d = zlib.decompressobj(wbits)
        self._started = False  # any input fed to the current member
        self.produced = 0

    def _input(self) -> bytes:
        if self._file is not None:
            try:
                return self._file.read(IN_CHUNK)
            except OSError as exc:
                raise FormatError(f"{self.path}: cannot read {self.what}: "
                                  f"{exc.strerror or exc}") from exc
        part = bytes(self._data[self._at:self._at + IN_CHUNK])
        self._at += len(part)
        return part

    def _bad(self, exc: Exception) -> FormatError:
        kind = {GZIP: "gzip", ZLIB: "zlib"}.get(self.wbits, "deflate")
        return FormatError(f"{self.path}: {self.what} is not a valid {kind} stream ({exc})")

    def _more(self, want: int) -> bytes:
        """Up to ``want`` (> 0) bytes of output; b"" only at the stream's clean end."""
        while True:
            d = self._d
            if d.eof:
                rest = d.unused_data or self._pending or self._input()
                self._pending = b""
                if self.wbits == GZIP:  # zero padding after a member is allowed (as gzip's)
                    rest = rest.lstrip(b"\x00")
                    while not rest:
                        more = self._input()
                        if not more:
                            return b""
                        rest = more.lstrip(b"\x00")
                if not rest:
                    return b""
                if self.wbits != GZIP:
                    raise FormatError(f"{self.path}: {self.what} has data after the end of "
                                      "its compressed stream")
                if not rest.startswith(_GZIP_MAGIC[:len(rest)]):
                    raise FormatError(f"{self.path}: {self.what} has data after the end of "
                                      "its gzip stream (not another gzip member)")
                self._d = zlib.decompressobj(self.wbits)
                self._pending = rest
                self._started = False
                continue
            data = d.unconsumed_tail or self._pending or self._input()
            self._pending = b""
            try:
                out = d.decompress(data, want)
            except zlib.error as exc:
                raise self._bad(exc) from None
            self._started |= bool(data)
            if out:
                self.produced += len(out)
                return out
            if not data and not d.eof:
                if not self._started and self.produced == 0:
                    raise FormatError(f"{self.path}: {self.what} is empty (a compressed "
                                      "stream expected)")
                raise FormatError(f"{self.path}: {self.what} ends inside its compressed "
                                  f"stream (after {self.produced:,} bytes of output): "
                                  "truncated")

    def read(self, n: int) -> bytes:
        """Up to ``n`` bytes (fewer only at the end of the stream)."""
        parts, got = [], 0
        while got < n:
            part = self._more(min(n - got, CHUNK))
            if not part:
                break
            parts.append(part)
            got += len(part)
        return b"".join(parts)

    def readinto(self, out: np.ndarray | memoryview | bytearray) -> int:
        """Fill ``out`` (bytes) from the stream; the number of bytes written (fewer than its
        length only at the end of the stream)."""
        view = memoryview(out).cast("B")
        got = 0
        while got < len(view):
            part = self._more(min(len(view) - got, CHUNK))
            if not part:
                break
            view[got:got + len(part)] = part
            got += len(part)
        return got

    def expect_end(self, declared: str) -> None:
        """Refuse a stream with output left (``declared``: what the header said it holds)."""
        if self._more(1):
            raise FormatError(f"{self.path}: {self.what} is longer than {declared}")

    def skip_to_end(self, limit: int, declared: str) -> int:
        """Inflate and discard the rest of the stream, refusing as soon as the total output
        passes ``limit`` bytes; the total output (a counting pass: memory of one chunk)."""
        while True:
            part = self._more(CHUNK)
            if not part:
                return self.produced
            if self.produced > limit:
                raise FormatError(f"{self.path}: {self.what} is longer than {declared}")


def inflate_gzip(source: Source, max_out: int, what: str, path: str | Path, *,
                 exact: bool = False) -> bytes:
    """The whole uncompressed content of a gzip stream (bytes or a binary file), refused as soon
    as it passes ``max_out`` bytes; with ``exact``, also refused when it ends short of it."""
    inflater = Inflater(source, path, what)
    out = inflater.read(max_out)
    if exact and len(out) < max_out:
        raise FormatError(f"{path}: {what} ends after {len(out):,} bytes, short of the "
                          f"{max_out:,} it declares")
    inflater.expect_end(f"the {max_out:,} bytes {'it declares' if exact else 'it may hold'}")
    return out


#: compression methods a bounded member read supports
ZIP_METHODS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflate"}


class _Window:
    """``size`` bytes of a file from ``start``, read as a stream (a ZIP member's compressed
    data); the file position is set on every read, so other readers may share the file."""

    def __init__(self, fp: BinaryIO, start: int, size: int) -> None:
        self.fp, self.pos, self.left = fp, start, size

    def read(self, n: int) -> bytes:
        self.fp.seek(self.pos)
        data = self.fp.read(min(n, self.left))
        self.pos += len(data)
        self.left -= len(data)
        return data


_LOCAL = struct.Struct("<IHHHHHIIIHH")  # a ZIP local file header


def inflate_zip_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo, max_out: int,
                       what: str, path: str | Path) -> bytearray:
    """One member of an open ZIP archive, at most ``max_out`` bytes: its declared size is
    checked first (against ``max_out``, its compressed size and the memory cap), then its
    compressed data is inflated a chunk at a time into a buffer of the declared size, refused
    as soon as the stream passes it or ends short of it, or fails its CRC."""
    name = info.filename
    if info.compress_type not in ZIP_METHODS:
        raise FormatError(f"{path}: {what} {name} uses ZIP compression method "
                          f"{info.compress_type}; expected stored (0) or deflate (8)")
    if info.flag_bits & 0x1:
        raise FormatError(f"{path}: {what} {name} is encrypted")
    declared = info.file_size
    if declared > max_out:
        raise FormatError(f"{path}: {what} {name} declares {declared:,} bytes, more than the "
                          f"{max_out:,} it can need")
    if info.compress_type == zipfile.ZIP_STORED and info.compress_size != declared:
        raise FormatError(f"{path}: {what} {name} is stored with {info.compress_size:,} bytes "
                          f"but declares {declared:,}")
    check_declared(path, f"{what} {name}", declared, info.compress_size)
    fp = archive.fp
    if fp is None:
        raise FormatError(f"{path}: the archive is closed")
    try:
        fp.seek(info.header_offset)
        head = fp.read(_LOCAL.size)
        if len(head) < _LOCAL.size or _LOCAL.unpack(head)[0] != 0x04034B50:
            raise FormatError(f"{path}: {what} {name}: bad local header (a ZIP archive "
                              "expected)")
        name_len, extra_len = _LOCAL.unpack(head)[9:]
        source = _Window(fp, info.header_offset + _LOCAL.size + name_len + extra_len,
                         info.compress_size)
        out = bytearray(declared)
        if info.compress_type == zipfile.ZIP_STORED:
            got = _read_stored(source, out)
        else:
            inflater = Inflater(source, path, f"{what} {name}", wbits=RAW)
            got = inflater.readinto(out)
            if got == declared:
                inflater.expect_end(f"the {declared:,} bytes it declares")
    except OSError as exc:
        raise FormatError(f"{path}: cannot read {what} {name}: {exc.strerror or exc}") from None
    if got != declared:
        raise FormatError(f"{path}: {what} {name} ends after {got:,} bytes, short of the "
                          f"{declared:,} it declares")
    if zlib.crc32(out) != info.CRC:
        raise FormatError(f"{path}: {what} {name} fails its CRC-32 check (corrupt)")
    return out


def _read_stored(source: _Window, out: bytearray) -> int:
    view = memoryview(out)
    got = 0
    while got < len(out):
        part = source.read(min(CHUNK, len(out) - got))
        if not part:
            break
        view[got:got + len(part)] = part
        got += len(part)
    view.release()
    return got
