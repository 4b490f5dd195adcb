"""``.spz`` (Niantic): a gzip stream of a 16-byte header and attribute arrays, versions 2 and 3.

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

Reads are bounded (:mod:`.inflate`): the header is inflated first, its declared stream size
(header + count x bytes per splat for its SH degree) is refused when the compressed bytes
cannot hold it (deflate expands at most ~1032x) or its decoded arrays cannot fit the machine's
memory, and the stream is inflated into a buffer of exactly that size, refused as soon as it
passes it or ends short (:func:`gunzip_blob`, :func:`decode_blob` for in-memory blobs).
"""

from __future__ import annotations

import gzip
import os
import struct
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ..errors import FormatError
from ..model import PointModel
from .inflate import Inflater, check_declared
from .regular import open_regular
from .splat_model import source_model
from .splats import (
    SH_COEFFS,
    SplatFields,
    fields_of,
    gaussian_table,
    logit,
    normalised_quaternions,
    note_lossy,
    restore_largest,
    sigmoid,
    table_source,
    write_blocks,
)

MAGIC = 0x5053474E
VERSIONS = (2, 3)
WRITE_VERSION = 3
HEADER = struct.Struct("<IIIBBBB")
COLOR_SCALE = 0.15
ALPHA_EPS = 0.5 / 255
# sign of each SH rest coefficient under the RDF <-> RUB flip (y -> -y, z -> -z)
SH_FLIP = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], dtype=np.float32)
FLIP = np.array([1.0, -1.0, -1.0])
# the same for glTF's LUF frame (x -> -x, y -> -y: 180 degrees about z)
LUF_SH_FLIP = np.array([-1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1], dtype=np.float32)
LUF_FLIP = np.array([-1.0, -1.0, 1.0])
RUB = (FLIP, SH_FLIP)
LUF = (LUF_FLIP, LUF_SH_FLIP)
GZIP_LEVEL = 1  # level 6 is 7x slower for ~3% smaller files


def _rot_bytes(version: int) -> int:
    return 3 if version == 2 else 4


def body_size(n: int, degree: int, version: int) -> int:
    return n * (9 + 1 + 3 + 3 + _rot_bytes(version) + 3 * SH_COEFFS[degree])


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
    if degree not in SH_COEFFS:
        raise FormatError(f"{path}: SPZ SH degree {degree}; expected 0 to 3")
    if frac > 23:
        raise FormatError(f"{path}: SPZ fractional bits {frac}; expected at most 23")
    return {"version": version, "count": count, "sh_degree": degree, "fractional_bits": frac,
            "antialiased": bool(flags & 1)}


def _refuse_plain(path: str | Path, head: bytes) -> None:
    """Data that starts with the SPZ magic itself (not gzip) is a newer layout (version 4
    keeps its header uncompressed): refuse it with one line naming the version."""
    if len(head) >= HEADER.size and HEADER.unpack_from(head)[0] == MAGIC:
        parse_header(path, head)  # raises for any version but 2 and 3
        raise FormatError(f"{path}: SPZ version 2/3 header outside a gzip stream; expected the "
                          "whole file gzip-compressed")


def stream_size(info: dict) -> int:
    """Bytes of the decompressed stream a header declares (the header and every array)."""
    return HEADER.size + body_size(info["count"], info["sh_degree"], info["version"])


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
    inflater = Inflater(source, path, what)
    head = inflater.read(HEADER.size)
    info = parse_header(path, head)
    want = stream_size(info)
    splats = f"the {info['count']:,} splats its header declares"
    if limit is not None and want > limit:
        raise FormatError(f"{path}: SPZ header declares {info['count']:,} splats ({want:,} "
                          "bytes), more than this reader's limit")
    check_declared(path, f"{what} (SPZ header: {info['count']:,} splats)", want, compressed,
                   decoded=decoded_size(info))
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
    raw = gunzip_blob(path, data, limit)
    return decode(raw, path, frame)


def read_stream(path: str | Path) -> np.ndarray:
    """The decompressed SPZ stream of a .spz file (opened through the one opener: a regular
    file), with :func:`gunzip_blob`'s bounds."""
    with open_regular(path, what="SPZ file") as fh:
        return _inflate(fh, path, os.fstat(fh.fileno()).st_size, "SPZ data")


def read_info(path: str | Path) -> dict:
    """The header fields of a .spz file (only its first bytes are inflated)."""
    with open_regular(path, what="SPZ file") as fh:
        _refuse_plain(path, fh.read(HEADER.size))
        fh.seek(0)
        head = Inflater(fh, path, "SPZ data").read(HEADER.size)
    return parse_header(path, head)


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
    put("opacity", logit(take(n).astype(np.float64) / 255, ALPHA_EPS))
    put("sh_dc", (take(3 * n).reshape(n, 3).astype(np.float64) / 255 - 0.5) / COLOR_SCALE)
    put("scale_log", take(3 * n).reshape(n, 3).astype(np.float64) / 16 - 10)
    if version == 2:
        xyz = take(3 * n).reshape(n, 3).astype(np.float64) / 127.5 - 1
        w = np.sqrt(np.maximum(0.0, 1 - (xyz**2).sum(axis=1)))
        q = np.concatenate([xyz, w[:, None]], axis=1)
    else:
        q = _v3_rotations(take(4 * n).view("<u4").copy())
    put("rotation", np.stack([q[:, 3], *(q[:, :3] * flip).T], axis=1))  # x y z conjugated
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


def encode(f: SplatFields, version: int = WRITE_VERSION, antialiased: bool = False,
           frame: tuple = RUB) -> bytearray:
    """The uncompressed SPZ stream of ``f`` (PLY space) stored in ``frame``; each field's codes
    are written straight into the one output buffer (no per-field byte copies to join)."""
    flip, sh_flip = frame
    n = f.count
    k = f.sh_rest.shape[2]
    frac = _fractional_bits(f.positions)
    degree = {c: d for d, c in SH_COEFFS.items()}[k]
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
        xyzw = np.concatenate([wxyz[:, 1:] * flip, wxyz[:, :1]], axis=1)
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
    raw = read_stream(path)
    info = parse_header(path, raw)
    table, views = gaussian_table(info["count"], 3 * SH_COEFFS[info["sh_degree"]])
    decode(raw, path, into=views)  # straight into the model's float32 table
    del raw
    return source_model(table_source(table, [f"read from an SPZ v{info['version']} file by "
                                             "splatdeform"]), path,
                        drop_nonfinite=drop_nonfinite)


def write_model(model: PointModel, path: Path, stream) -> None:
    fields = fields_of(model, path, ".spz")
    note_lossy(path, ".spz", "positions 24-bit fixed point, opacity, colour, log scale 8 bits, "
               "rotation 10 bits per component, SH rest 5 bits (degree 1) and 4 bits (2-3)",
               model)
    with gzip.GzipFile(filename="", fileobj=stream, mode="wb", compresslevel=GZIP_LEVEL,
                       mtime=0) as gz:  # no file name in the header: the same bytes each time
        gz.write(encode(fields))
