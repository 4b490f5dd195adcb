"""``.spz`` (Niantic): versions 2 and 3 (a gzip stream of a 16-byte header and attribute arrays)
and version 4 (a 32-byte plaintext header, extension records, a table of contents and one
ZSTD stream per attribute); written as version 4 by default (:data:`WRITE_VERSION`).

Header (little-endian): magic 0x5053474e, version, splat count, SH degree, fractional bits of
the fixed-point positions, flags (bit 0: antialiased), reserved. Arrays, each for every splat in
turn: positions (3 x 24-bit signed fixed point), alphas (uint8 sigmoid), colours (uint8,
f_dc * 0.15 * 255 + 127.5), scales (uint8, (log scale + 10) * 16), rotations (v2: x y z of the
unit quaternion with w >= 0 as uint8 127.5 * (1 + c); v3: 32 bits, the index of the largest
component in the top two bits and the other three as sign + 9-bit magnitude scaled by sqrt(2),
the highest index in the lowest bits), SH rest (uint8 128 + 128 * c, coefficient-major with r g b
inside; degree-1 values on a grid of 8 codes, higher ones 16).

Axes: SPZ stores RUB (x right, y up, z back); PLY space is RDF, so y and z flip both ways
(positions, the quaternion's y and z, and the SH coefficients odd in y + z). An SPZ blob inside
glTF (``KHR_gaussian_splatting_compression_spz``) is packed in glTF's LUF frame instead (that
specification says so): x and y flip (:data:`LUF`).

Version 4 (layout facts: ``shared/formats/SPZ_v4.md``): header u32 magic, version, count, u8
SH degree (0-4), fractional bits, flags (0x1 antialiased, 0x2 extensions), stream count, u32
table offset, 12 reserved bytes; extension records (u32 type, u32 length, payload) up to the
table; the table's N x (u64 compressed, u64 uncompressed) sizes; the N streams (positions,
alphas, colours, scales, rotations, SH), each v3's encoding of that attribute (so a v4 file
decodes through the same code as a v3 stream laid end to end). Extension records are kept on
read (as ``spz_extension TYPE HEX`` comments of the model's source) and written back; the
Adobe coordinate-system record (0xADBE0003) is honoured on read (the data is converted from its
frame to PLY space, and written back in RUB without it); a frame we cannot convert is refused.
Bounds: every stream's uncompressed size must equal what the count implies, the compressed
sizes must fill the file exactly, each ZSTD frame's declared content size (when stated) must
match, no stream may expand more than ZSTD can (:data:`ZSTD_MAX_RATIO`), the decoded table must
fit memory, and each stream is inflated with that maximum output. Streams are written at ZSTD
level :data:`ZSTD_LEVEL` (the reference writer's: splat-transform's files are within 1% of
ours), v3 at gzip level :data:`GZIP_LEVEL`.

Reads are bounded (:mod:`.inflate`): the header is inflated first, its declared stream size
(header + count x bytes per splat for its SH degree) is refused when the compressed bytes
cannot hold it (deflate expands at most ~1032x) or its decoded arrays cannot fit the machine's
memory, and the stream is inflated into a buffer of exactly that size, refused as soon as it
passes it or ends short (:func:`gunzip_blob`, :func:`decode_blob` for in-memory blobs).
"""

from __future__ import annotations

import gzip
import io
import os
import struct
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ..errors import ConfigError, FormatError
from ..model import PointModel
from .inflate import Inflater, check_declared
from .regular import open_regular
from .splat_model import source_model
from .splats import (
    SH_COEFFS,
    SplatFields,
    alpha_logit,
    fields_of,
    gaussian_table,
    normalised_quaternions,
    note_lossy,
    restore_largest,
    sigmoid,
    table_source,
    write_blocks,
)

MAGIC = 0x5053474E
VERSIONS = (2, 3, 4)
WRITE_VERSION = 4
#: versions a writer can be asked for (``save.spz_version``, ``deform --spz-version``)
WRITE_VERSIONS = (3, 4)
HEADER = struct.Struct("<IIIBBBB")
V4_HEADER = struct.Struct("<IIIBBBBI12s")
TOC_ENTRY = struct.Struct("<QQ")
#: ZSTD level of the v4 streams (the reference writer's sizes, measured)
ZSTD_LEVEL = 12
#: the most a ZSTD frame can expand (an RLE block: 128 KiB from a 4-byte block) plus slack
ZSTD_MAX_RATIO = 32768
ZSTD_SLACK = 1 << 17
EXTENSIONS_FLAG = 0x2
#: a splat file's decompressed stream may be at most this many times its compressed bytes
#: (plus :data:`PLAUSIBLE_SLACK`): real scenes compress 1.3-4x (measured: the guitar 1.3x, the
#: SH3 tile 3.9x; v3 and v4 alike). deflate (1032x) and ZSTD (32768x) could expand far more, so
#: a small file declaring many splats would otherwise allocate gigabytes before its streams
#: prove (or fail to prove) what it declares; a writer refuses a scene that compresses beyond
#: it (what we write, we read back)
PLAUSIBLE_RATIO = 64
PLAUSIBLE_SLACK = 16 << 20
#: extension records kept as source comments (hex text) on read: at most this many bytes of
#: payload in all (a PLY header holds at most 1 MiB); beyond it they are dropped with a warning
MAX_KEPT_EXTENSION_BYTES = 64 << 10
#: the Adobe coordinate-system extension (payload: the frame's code, u8 or u32)
COORDINATE_SYSTEM = 0xADBE0003
#: comment prefix keeping an extension record in a model's source
EXTENSION_COMMENT = "spz_extension"
COLOR_SCALE = 0.15
# sign of each SH rest coefficient under the RDF <-> RUB flip (y -> -y, z -> -z)
SH_FLIP = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], dtype=np.float32)
FLIP = np.array([1.0, -1.0, -1.0])
# the same for glTF's LUF frame (x -> -x, y -> -y: 180 degrees about z)
LUF_SH_FLIP = np.array([-1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1], dtype=np.float32)
LUF_FLIP = np.array([-1.0, -1.0, 1.0])
GZIP_LEVEL = 6  # the reference writer's size (level 1 is 1-2% larger)
#: the Adobe extension's frame codes (the reference enum's order): axis signs of each
#: "standard family" frame relative to RDF (PLY space); the rotated family is refused
FRAMES = {1: "LDB", 2: "RDB", 3: "LUB", 4: "RUB", 5: "LDF", 6: "RDF", 7: "LUF", 8: "RUF"}


def frame_of(name: str) -> tuple:
    """(position signs, SH rest signs) converting a standard-family frame (e.g. ``"RUB"``) to
    PLY space (RDF) and back: a diagonal flip, its SH signs from the basis' parities."""
    from ..geometry import sh_basis

    flip = np.array([1.0 if name[0] == "R" else -1.0, 1.0 if name[1] == "D" else -1.0,
                     1.0 if name[2] == "F" else -1.0])
    d = np.array([0.31, 0.57, 0.76])
    sh = np.sign(sh_basis(d * flip, 4) / sh_basis(d, 4)).astype(np.float32)
    return flip, sh


def _quat_flip(flip: np.ndarray) -> np.ndarray:
    """Signs of a quaternion's x y z under the diagonal flip (a reflection acts as its negative,
    a proper rotation)."""
    return flip * float(np.prod(flip))


RUB = frame_of("RUB")
LUF = frame_of("LUF")


def _rot_bytes(version: int) -> int:
    return 3 if version == 2 else 4


def stream_bytes(degree: int, version: int) -> tuple[int, ...]:
    """Bytes per splat of each attribute, in stream order (positions, alphas, colours, scales,
    rotations, SH; no SH entry for degree 0)."""
    sizes = (9, 1, 3, 3, _rot_bytes(version))
    return sizes + ((3 * SH_COEFFS[degree],) if degree else ())


def body_size(n: int, degree: int, version: int) -> int:
    return n * sum(stream_bytes(degree, version))


def parse_header(path: str | Path, head: bytes) -> dict:
    """The header fields (raises FormatError with one line for a bad or unknown header)."""
    if len(head) < HEADER.size:
        raise FormatError(f"{path}: not an SPZ file (shorter than its 16-byte header)")
    magic, version, count, degree, frac, flags, _ = HEADER.unpack_from(head)
    if magic != MAGIC:
        raise FormatError(f"{path}: not an SPZ file (magic {magic:#010x}, expected "
                          f"{MAGIC:#010x} 'NGSP')")
    if version not in VERSIONS:
        raise FormatError(f"{path}: SPZ version {version} is not supported (versions "
                          f"{', '.join(map(str, VERSIONS))} are)")
    top = 4 if version == 4 else 3
    if degree > top:
        raise FormatError(f"{path}: SPZ SH degree {degree}; expected 0 to {top}")
    if frac > 23:
        raise FormatError(f"{path}: SPZ fractional bits {frac}; expected at most 23")
    return {"version": version, "count": count, "sh_degree": degree, "fractional_bits": frac,
            "antialiased": bool(flags & 1)}


def is_v4(head: bytes | bytearray | memoryview) -> bool:
    """True when ``head`` starts with the plaintext magic (a version-4 file; v2/v3 are gzip)."""
    return len(head) >= 4 and int.from_bytes(bytes(head[:4]), "little") == MAGIC


def _refuse_plain(path: str | Path, head: bytes) -> None:
    """Data that starts with the SPZ magic itself (not gzip) must be version 4 (it keeps its
    header uncompressed); refuse a plaintext v2/v3 header with one line."""
    if len(head) >= HEADER.size and HEADER.unpack_from(head)[0] == MAGIC:
        info = parse_header(path, head)  # raises for an unknown version
        if info["version"] != 4:
            raise FormatError(f"{path}: SPZ version {info['version']} header outside a gzip "
                              "stream; expected the whole file gzip-compressed")


def _refuse_gzipped_v4(path: str | Path, info: dict) -> None:
    if info["version"] == 4:
        raise FormatError(f"{path}: SPZ version 4 inside a gzip stream; version 4 keeps its "
                          "header uncompressed")


def stream_size(info: dict) -> int:
    """Bytes of the decompressed stream a header declares (the header and every array)."""
    return HEADER.size + body_size(info["count"], info["sh_degree"], info["version"])


def check_plausible(path: str | Path, info: dict, compressed: int) -> None:
    """Refuse (one line naming the file and what it declares) a header whose stream is more
    than :data:`PLAUSIBLE_RATIO` x the ``compressed`` bytes (+ :data:`PLAUSIBLE_SLACK`): checked
    before anything is allocated or inflated."""
    want = stream_size(info)
    if want > PLAUSIBLE_RATIO * compressed + PLAUSIBLE_SLACK:
        raise FormatError(f"{path}: SPZ header declares {info['count']:,} splats ({want:,} "
                          f"bytes of attributes) in {compressed:,} compressed bytes; splat data "
                          f"compresses at most {PLAUSIBLE_RATIO}x (+{PLAUSIBLE_SLACK >> 20} MiB) "
                          "here: refused before allocating")


def decoded_size(info: dict) -> int:
    """Bytes of the decompressed stream and the float32 table it decodes to (what a read
    holds at its peak, besides small temporaries)."""
    return stream_size(info) + info["count"] * 4 * (14 + 3 * SH_COEFFS[info["sh_degree"]])


def _inflate(source: BinaryIO | bytes | bytearray | memoryview, path: str | Path,
             compressed: int, what: str, limit: int | None = None) -> np.ndarray:
    """The decompressed SPZ stream (uint8) of ``source`` (a binary file at its start, or the
    gzip'd bytes) of ``compressed`` bytes: the header is inflated first and its declared size
    checked against the compressed size and the memory cap; the rest is inflated into one
    buffer of exactly that size, refused as soon as the stream passes it or ends short. When
    the gzip trailer states another size (a bomb, a cut stream, or several members), a counting
    pass (one chunk of memory) checks the stream's length before the buffer is allocated."""
    if hasattr(source, "read"):
        first = source.read(HEADER.size)
        source.seek(max(compressed - 4, 0))
        trailer = source.read(4)
        source.seek(0)
    else:
        first, trailer = bytes(source[:HEADER.size]), bytes(source[-4:])
    _refuse_plain(path, first)
    if is_v4(first):
        return read_v4(path, source if not hasattr(source, "read") else source.read(),
                       limit)[0]
    inflater = Inflater(source, path, what)
    head = inflater.read(HEADER.size)
    info = parse_header(path, head)
    _refuse_gzipped_v4(path, info)
    want = stream_size(info)
    splats = f"the {info['count']:,} splats its header declares"
    if limit is not None and want > limit:
        raise FormatError(f"{path}: SPZ header declares {info['count']:,} splats ({want:,} "
                          "bytes), more than this reader's limit")
    check_declared(path, f"{what} (SPZ header: {info['count']:,} splats)", want, compressed,
                   decoded=decoded_size(info))
    check_plausible(path, info, compressed)
    isize = int.from_bytes(trailer, "little") if compressed >= 18 else None
    if isize != want % (1 << 32):
        if hasattr(source, "read"):
            source.seek(0)
        total = Inflater(source, path, what).skip_to_end(want, splats)
        if total < want:
            raise FormatError(f"{path}: SPZ body is shorter than {splats}")
        if hasattr(source, "read"):
            source.seek(0)
        inflater = Inflater(source, path, what)
        inflater.read(HEADER.size)
    raw = np.empty(want, dtype=np.uint8)
    raw[:HEADER.size] = np.frombuffer(head, dtype=np.uint8)
    if inflater.readinto(raw[HEADER.size:]) < want - HEADER.size:
        raise FormatError(f"{path}: SPZ body is shorter than {splats}")
    inflater.expect_end(splats)
    return raw


def _v4_frame(path: str | Path, payload: bytes) -> tuple | None:
    """The frame an Adobe coordinate-system record names (None: the specification's RUB);
    one FormatError line for a frame this reader cannot convert."""
    if len(payload) not in (1, 4):
        raise FormatError(f"{path}: SPZ coordinate-system extension of {len(payload)} bytes; "
                          "expected 1 or 4 (the frame's code)")
    code = int.from_bytes(payload, "little")
    if code in (0, 4):  # unspecified: the specification's default frame
        return None
    if code not in FRAMES:
        raise FormatError(f"{path}: SPZ coordinate-system extension names frame {code} (the "
                          "90-degree rotated family or unknown); only the RUB/RDF-style "
                          "frames (codes 0-8) are read")
    return frame_of(FRAMES[code])


def _v4_records(path: str | Path, data: bytes | memoryview, end: int) -> list[tuple[int, bytes]]:
    """The extension records (type, payload) in [32, end), each checked to lie inside."""
    records, at = [], V4_HEADER.size
    while at < end:
        if end - at < 8:
            raise FormatError(f"{path}: SPZ extension record at byte {at} is cut by the table "
                              f"of contents at {end}")
        kind, length = struct.unpack_from("<II", data, at)
        if kind == 0:
            raise FormatError(f"{path}: SPZ extension record of type 0 at byte {at} (type 0 is "
                              "not used)")
        if length > end - at - 8:
            raise FormatError(f"{path}: SPZ extension record {kind:#010x} declares {length:,} "
                              f"bytes, past the table of contents at byte {end}")
        records.append((kind, bytes(data[at + 8:at + 8 + length])))
        at += 8 + length
    return records


def parse_v4(path: str | Path, data: bytes | bytearray | memoryview) -> dict:
    """The header, extension records and stream table of a version-4 file (everything but
    the streams), every size checked against the file and the count."""
    size = len(data)
    if size < V4_HEADER.size:
        raise FormatError(f"{path}: SPZ version 4 file shorter than its 32-byte header")
    info = parse_header(path, bytes(data[:HEADER.size]))
    _, version, n, degree, frac, flags, streams, toc, _ = V4_HEADER.unpack_from(data)
    if version != 4:
        raise FormatError(f"{path}: SPZ version {version} header outside a gzip stream; "
                          "expected the whole file gzip-compressed")
    want = 5 + (degree > 0)
    if streams != want:
        raise FormatError(f"{path}: SPZ header declares {streams} streams; SH degree {degree} "
                          f"needs {want}")
    if toc < V4_HEADER.size or toc + TOC_ENTRY.size * streams > size:
        raise FormatError(f"{path}: SPZ table of contents at byte {toc:,} ({streams} entries) "
                          f"lies outside the {size:,}-byte file")
    records = _v4_records(path, data, toc)
    frame = None
    for kind, payload in records:
        if kind == COORDINATE_SYSTEM:
            frame = _v4_frame(path, payload)
    at = toc + TOC_ENTRY.size * streams
    table = [TOC_ENTRY.unpack_from(data, toc + TOC_ENTRY.size * i) for i in range(streams)]
    names = ("positions", "alphas", "colours", "scales", "rotations", "SH")
    for name, per, (packed, plain) in zip(names, stream_bytes(degree, 4), table, strict=False):
        if plain != n * per:
            raise FormatError(f"{path}: SPZ {name} stream declares {plain:,} bytes "
                              f"uncompressed; the {n:,} splats its header declares need "
                              f"{n * per:,}")
        if plain > ZSTD_MAX_RATIO * packed + ZSTD_SLACK:
            raise FormatError(f"{path}: SPZ {name} stream declares {plain:,} bytes from "
                              f"{packed:,} compressed bytes (ZSTD expands at most "
                              f"{ZSTD_MAX_RATIO}x)")
    packed_total = sum(c for c, _ in table)
    if packed_total != size - at:
        raise FormatError(f"{path}: SPZ table of contents declares {packed_total:,} compressed "
                          f"bytes; the file holds {size - at:,} after it")
    check_plausible(path, info, size)
    info.update(streams=table, data_offset=at, extensions=records, frame=frame,
                antialiased=bool(flags & 1))
    return info


def read_v4(path: str | Path, data: bytes | bytearray | memoryview,
            limit: int | None = None) -> tuple[np.ndarray, dict]:
    """(the v3-layout stream: a 16-byte header of version 4 and the arrays end to end, the
    header fields with ``extensions`` and ``frame``) of a version-4 file's bytes. Each stream
    is inflated with a maximum output of its declared size (refused when it states or
    produces another size)."""
    import zstandard

    info = parse_v4(path, data)
    want = stream_size(info)
    if limit is not None and want > limit:
        raise FormatError(f"{path}: SPZ header declares {info['count']:,} splats ({want:,} "
                          "bytes), more than this reader's limit")
    check_declared(path, f"SPZ data (SPZ header: {info['count']:,} splats)", want,
                   decoded=decoded_size(info))
    raw = np.empty(want, dtype=np.uint8)
    raw[:HEADER.size] = np.frombuffer(bytes(data[:HEADER.size]), dtype=np.uint8)
    view = memoryview(data)
    at, out = info["data_offset"], HEADER.size
    dctx = zstandard.ZstdDecompressor()
    for i, (packed, plain) in enumerate(info["streams"]):
        frame = view[at:at + packed]
        try:
            declared = zstandard.frame_content_size(frame)
        except zstandard.ZstdError as exc:
            raise FormatError(f"{path}: SPZ stream {i} is not a ZSTD frame ({exc})") from None
        if declared not in (-1, plain):
            raise FormatError(f"{path}: SPZ stream {i}'s ZSTD frame declares {declared:,} "
                              f"bytes; the table of contents says {plain:,}")
        try:
            part = dctx.decompress(frame, max_output_size=plain) if plain else b""
        except zstandard.ZstdError as exc:
            raise FormatError(f"{path}: SPZ stream {i} does not inflate to its declared "
                              f"{plain:,} bytes ({exc})") from None
        if len(part) != plain:
            raise FormatError(f"{path}: SPZ stream {i} inflates to {len(part):,} bytes; the "
                              f"table of contents says {plain:,}")
        raw[out:out + plain] = np.frombuffer(part, dtype=np.uint8)
        del part
        at += packed
        out += plain
    return raw, info


def write_v4(stream: bytes | bytearray, extensions: list[tuple[int, bytes]] = (),
             level: int = ZSTD_LEVEL) -> bytes:
    """A version-4 file of the v3-layout stream :func:`encode` built with version 4: the
    32-byte header, ``extensions`` (type, payload) records, the table and one ZSTD frame per
    attribute (with its content size)."""
    import zstandard

    _, _, n, degree, frac, flags, _ = HEADER.unpack_from(stream)
    cctx = zstandard.ZstdCompressor(level=level, write_content_size=True, write_checksum=False)
    view = memoryview(stream)
    at, frames, table = HEADER.size, [], []
    for per in stream_bytes(degree, 4):
        frames.append(cctx.compress(view[at:at + n * per]))
        table.append(TOC_ENTRY.pack(len(frames[-1]), n * per))
        at += n * per
    records = b"".join(struct.pack("<II", kind, len(p)) + p for kind, p in extensions)
    flags = (flags & 1) | (EXTENSIONS_FLAG if records else 0)
    head = V4_HEADER.pack(MAGIC, 4, n, degree, frac, flags, len(frames),
                          V4_HEADER.size + len(records), bytes(12))
    return b"".join([head, records, *table, *frames])


def extension_comments(records: list[tuple[int, bytes]], path: str | Path = "SPZ file"
                       ) -> list[str]:
    """Source comments keeping extension records (the coordinate-system one is consumed); more
    than :data:`MAX_KEPT_EXTENSION_BYTES` of them (8 bytes of record head and the payload
    each) are dropped, all of them, with one warning naming ``path`` (kept, they would make a
    header that no PLY reader, ours included, reads back)."""
    kept = [(kind, payload) for kind, payload in records if kind != COORDINATE_SYSTEM]
    total = sum(8 + len(payload) for _, payload in kept)
    if total > MAX_KEPT_EXTENSION_BYTES:
        warnings.warn(f"{path}: {len(kept):,} SPZ extension records of {total:,} bytes in all "
                      f"(more than {MAX_KEPT_EXTENSION_BYTES >> 10} KiB) are not kept: an "
                      "output will not carry them", stacklevel=2)
        return []
    return [f"{EXTENSION_COMMENT} {kind:#010x} {payload.hex()}" for kind, payload in kept]


def extensions_of(model: PointModel) -> list[tuple[int, bytes]]:
    """The extension records a model read from SPZ v4 keeps in its source's comments."""
    out = []
    for line in getattr(model.source, "comments", None) or ():
        parts = line.split()
        if len(parts) in (2, 3) and parts[0] == EXTENSION_COMMENT:
            try:
                out.append((int(parts[1], 16), bytes.fromhex(parts[2] if len(parts) == 3
                                                              else "")))
            except ValueError:
                continue
    return out


def gunzip_blob(path: str | Path, data: bytes | bytearray | memoryview,
                limit: int | None = None) -> np.ndarray:
    """The decompressed SPZ stream (uint8 array) of an in-memory gzip'd blob (glTF's SPZ
    extension) named by ``path`` in errors, inflated with a maximum output of what its header
    declares (refused as soon as it passes it or ends short; a declared size its compressed
    bytes cannot hold or the memory cannot take is refused before inflating). ``limit``: a
    further cap on the decompressed bytes."""
    return _inflate(data, path, len(data), "SPZ data", limit)


def decode_blob(path: str | Path, data: bytes | bytearray | memoryview, frame: tuple = RUB,
                limit: int | None = None) -> tuple[SplatFields, dict]:
    """The splat fields (PLY space) and header of a gzip'd SPZ blob stored in ``frame`` (RUB
    for a .spz file, :data:`LUF` for glTF's SPZ extension), with :func:`gunzip_blob`'s
    bounds."""
    if is_v4(data):
        raw, info = read_v4(path, data, limit)
        return decode(raw, path, info.get("frame") or frame)
    raw = gunzip_blob(path, data, limit)
    return decode(raw, path, frame)


def read_file(path: str | Path) -> tuple[np.ndarray, dict]:
    """(the decompressed stream, the header fields; for v4 with ``extensions`` and ``frame``)
    of a .spz file, read through the one opener."""
    with open_regular(path, what="SPZ file") as fh:
        size = os.fstat(fh.fileno()).st_size
        if is_v4(fh.read(4)):
            fh.seek(0)
            data = fh.read()
            if len(data) != size:
                raise FormatError(f"{path}: SPZ file changed while it was read")
            return read_v4(path, data)
        fh.seek(0)
        raw = _inflate(fh, path, size, "SPZ data")
    return raw, parse_header(path, raw)


def read_info(path: str | Path) -> dict:
    """The header fields of a .spz file (only its first bytes are inflated; a v4 file's
    header, extension records and table are read and checked)."""
    with open_regular(path, what="SPZ file") as fh:
        head = fh.read(HEADER.size)
        if is_v4(head):
            fh.seek(0)
            return parse_v4(path, fh.read())
        _refuse_plain(path, head)
        fh.seek(0)
        head = Inflater(fh, path, "SPZ data").read(HEADER.size)
    info = parse_header(path, head)
    _refuse_gzipped_v4(path, info)
    return info


def _v3_rotations(words: np.ndarray) -> np.ndarray:
    """(N,) uint32 -> (N, 4) x y z w: the three kept components in index order sit in bits
    20-29, 10-19 and 0-9 (the highest index lowest), each a sign bit over 9 magnitude bits."""
    kept = np.empty((len(words), 3))
    for j, shift in enumerate((20, 10, 0)):
        field = words >> np.uint32(shift)
        mag = (field & np.uint32(511)).astype(np.float64) / 511 * np.sqrt(0.5)
        kept[:, j] = np.where((field & np.uint32(512)) != 0, -mag, mag)
    return restore_largest(kept, (words >> np.uint32(30)).astype(np.intp))


def _v3_words(q_xyzw: np.ndarray) -> np.ndarray:
    n = len(q_xyzw)
    largest = np.argmax(np.abs(q_xyzw), axis=1)
    q = q_xyzw * np.where(q_xyzw[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]
    words = np.zeros(n, dtype=np.uint32)
    for i in range(4):
        use = largest != i
        mag = np.clip(np.round(np.abs(q[:, i]) / np.sqrt(0.5) * 511), 0, 511).astype(np.uint32)
        code = mag | (np.uint32(1 << 9) * (q[:, i] < 0).astype(np.uint32))
        words = np.where(use, (words << np.uint32(10)) | code, words)
    return words | (largest.astype(np.uint32) << np.uint32(30))


def decode(raw: bytes, path: str | Path, frame: tuple = RUB,
           into: dict[str, np.ndarray] | None = None) -> tuple[SplatFields, dict]:
    """The splat fields in PLY space of a decompressed SPZ stream stored in ``frame`` (RUB, or
    LUF for glTF's SPZ extension). into: the column views of a :func:`gaussian_table` to
    decode into (the returned fields are then those views)."""
    flip, sh_flip = frame
    info = parse_header(path, raw)
    n, degree, version = info["count"], info["sh_degree"], info["version"]
    k = SH_COEFFS[degree]
    if len(raw) != stream_size(info):
        raise FormatError(f"{path}: SPZ stream is {len(raw):,} bytes; its header declares "
                          f"{n:,} splats ({stream_size(info):,} bytes)")
    buf = np.frombuffer(raw, dtype=np.uint8, offset=HEADER.size)
    at = 0

    def take(size: int) -> np.ndarray:
        nonlocal at
        part = buf[at:at + size]
        at += size
        return part

    out: dict[str, np.ndarray] = {}

    def put(name: str, value: np.ndarray) -> None:
        """Keep a decoded field: float32 (positions float64), or written into ``into``."""
        if into is None:
            out[name] = value if name == "positions" else value.astype(np.float32)
        else:
            into[name][:] = value.reshape(n, -1)
            out[name] = into[name]

    p = take(9 * n).reshape(n, 3, 3).astype(np.int32)
    fixed = p[..., 0] | (p[..., 1] << 8) | (p[..., 2] << 16)
    del p
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    put("positions", fixed.astype(np.float64) / (1 << info["fractional_bits"]) * flip)
    del fixed
    alpha = take(n)  # 255 / 0 are alpha 1 / 0: logits +-inf (the reference reads 1 -+ 1e-6)
    put("opacity", alpha_logit(alpha / 255))
    put("sh_dc", (take(3 * n).reshape(n, 3).astype(np.float64) / 255 - 0.5) / COLOR_SCALE)
    put("scale_log", take(3 * n).reshape(n, 3).astype(np.float64) / 16 - 10)
    if version == 2:
        xyz = take(3 * n).reshape(n, 3).astype(np.float64) / 127.5 - 1
        w = np.sqrt(np.maximum(0.0, 1 - (xyz**2).sum(axis=1)))
        q = np.concatenate([xyz, w[:, None]], axis=1)
    else:
        q = _v3_rotations(take(4 * n).view("<u4").copy())
    put("rotation", np.stack([q[:, 3], *(q[:, :3] * _quat_flip(flip)).T], axis=1))
    del q
    # SH rest in place in one (N, 3, K) float32 array (the largest decoded field: no temporaries)
    sh_rest = np.empty((n, 3, k), dtype=np.float32) if into is None else \
        into["sh_rest"].reshape(n, 3, k)
    np.subtract(take(3 * k * n).reshape(n, k, 3).transpose(0, 2, 1), np.float32(128),
                out=sh_rest)
    sh_rest *= sh_flip[:k] / np.float32(128)
    return SplatFields(**out, sh_rest=sh_rest), info


def _fractional_bits(positions: np.ndarray) -> int:
    """The most fractional bits (up to 12) with which every coordinate fits 24 bits."""
    top = float(np.abs(positions).max()) if positions.size else 0.0
    for bits in range(12, -1, -1):
        if top * (1 << bits) < (1 << 23) - 1:
            return bits
    raise FormatError(f"a coordinate of magnitude {top:g} does not fit SPZ's 24-bit positions")


def _sh_codes(values: np.ndarray, step: int) -> np.ndarray:
    """SH values -> uint8 codes 128 + 128 * v on a grid of ``step`` codes (float32 math)."""
    q = np.asarray(values, dtype=np.float32) * np.float32(128 / step) + np.float32(128 / step)
    np.rint(q, out=q)
    q *= step
    return np.clip(q, 0, 255).astype(np.uint8)


def encode(f: SplatFields, version: int = 3, antialiased: bool = False,
           frame: tuple = RUB) -> bytearray:
    """The uncompressed SPZ stream of ``f`` (PLY space) stored in ``frame``; each field's codes
    are written straight into the one output buffer (no per-field byte copies to join)."""
    flip, sh_flip = frame
    n = f.count
    k = f.sh_rest.shape[2]
    frac = _fractional_bits(f.positions)
    degree = {c: d for d, c in SH_COEFFS.items()}[k]
    if degree > 3 and version < 4:
        raise FormatError(f"SPZ version {version} holds SH degrees 0-3; this scene has degree "
                          f"{degree} (write version 4)")
    sizes = (9, 1, 3, 3, 3 if version == 2 else 4, 3 * k)  # bytes per splat of each field
    out = bytearray(HEADER.size + n * sum(sizes))
    out[:HEADER.size] = HEADER.pack(MAGIC, version, n, degree, frac, int(antialiased), 0)
    ends = np.cumsum((0, *sizes)) * n
    pos, alpha, color, scale, rot, codes = (
        np.frombuffer(out, np.uint8, count=n * size, offset=HEADER.size + at).reshape(n, size)
        for at, size in zip(ends[:-1], sizes, strict=True))
    fixed = np.round(f.positions * flip * (1 << frac)).astype(np.int64) & 0xFFFFFF
    for byte in range(3):  # little-endian 24-bit per axis
        pos[:, byte::3] = (fixed >> (8 * byte)) & 0xFF
    del fixed
    alpha[:, 0] = np.clip(np.round(sigmoid(f.opacity) * 255), 0, 255)
    color[:] = np.clip(np.round(f.sh_dc.astype(np.float64) * (COLOR_SCALE * 255) + 127.5), 0,
                       255)
    scale[:] = np.clip(np.round((f.scale_log.astype(np.float64) + 10) * 16), 0, 255)
    codes = codes.reshape(n, k, 3)
    for rows in write_blocks(n):  # bounded float temporaries
        wxyz = normalised_quaternions(f.rotation[rows])
        xyzw = np.concatenate([wxyz[:, 1:] * _quat_flip(flip), wxyz[:, :1]], axis=1)
        if version == 2:
            xyzw = xyzw * np.where(xyzw[:, 3] < 0, -1.0, 1.0)[:, None]
            rot[rows] = np.clip(np.round((xyzw[:, :3] + 1) * 127.5), 0, 255)
        else:
            rot[rows] = _v3_words(xyzw).astype("<u4").view(np.uint8).reshape(-1, 4)
        if k:
            sh = (f.sh_rest[rows] * sh_flip[:k]).transpose(0, 2, 1)  # (B, K, 3)
            codes[rows, :3] = _sh_codes(sh[:, :3], 8)
            codes[rows, 3:] = _sh_codes(sh[:, 3:], 16)
    return out


def read_model(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    raw, info = read_file(path)
    table, views = gaussian_table(info["count"], 3 * SH_COEFFS[info["sh_degree"]])
    decode(raw, path, info.get("frame") or RUB, into=views)  # straight into the float32 table
    del raw
    comments = [f"read from an SPZ v{info['version']} file by splatdeform",
                *extension_comments(info.get("extensions", []), path)]
    return source_model(table_source(table, comments), path, drop_nonfinite=drop_nonfinite)


_WRITE_VERSION: ContextVar[int] = ContextVar("spz_write_version", default=WRITE_VERSION)


@contextmanager
def writing_version(version: int | None) -> Iterator[None]:
    """Writes of .spz inside this block use ``version`` (3 or 4; None: the default,
    :data:`WRITE_VERSION`): ``save.spz_version`` / ``deform --spz-version``."""
    if version is None:
        yield
        return
    if version not in WRITE_VERSIONS:
        raise ConfigError(f"save.spz_version: expected 3 or 4, got {version!r}")
    token = _WRITE_VERSION.set(int(version))
    try:
        yield
    finally:
        _WRITE_VERSION.reset(token)


def write_model(model: PointModel, path: Path, stream, version: int | None = None) -> None:
    """Write ``model`` as SPZ ``version`` (default: :func:`writing_version`'s, else 4): v4 keeps
    SH degree 4 and the extension records the model was read with; v3 drops band 4 (said)."""
    version = _WRITE_VERSION.get() if version is None else version
    top = 4 if version == 4 else 3
    fields = fields_of(model, path, ".spz", max_degree=top)
    note_lossy(path, f".spz (v{version})", "positions 24-bit fixed point, opacity, colour, "
               "log scale 8 bits, rotation 10 bits per component, SH rest 5 bits (degree 1) and "
               "4 bits (2-4)", model, sh_kept=3 * ((top + 1) ** 2 - 1))
    raw = encode(fields, version=version)
    if version == 4:
        data = write_v4(raw, extensions_of(model))
    else:
        out = io.BytesIO()
        with gzip.GzipFile(filename="", fileobj=out, mode="wb", compresslevel=GZIP_LEVEL,
                           mtime=0) as gz:  # no file name in the header: the same bytes each time
            gz.write(raw)
        data = out.getvalue()
    if len(raw) > PLAUSIBLE_RATIO * len(data) + PLAUSIBLE_SLACK:
        raise FormatError(f"{path}: {fields.count:,} splats compress from {len(raw):,} to "
                          f"{len(data):,} bytes, more than the {PLAUSIBLE_RATIO}x an SPZ reader "
                          "here accepts (a scene of near-identical splats); write .ply instead")
    stream.write(data)
