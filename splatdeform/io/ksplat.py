"""``.ksplat``: the splat buffer of the GaussianSplats3D viewer (npm
``@mkkellogg/gaussian-splats-3d``), read only.

There is no written specification; the layout below was learned from that library's source
(version 0.4.7) and checked against its own converter's files and splat-transform 3.7.0's
reader. Little-endian throughout.

- Main header, 4096 bytes: u8 major version (0) and minor version (>= 1) at 0 and 1; u32 at 4:
  the number of sections (their headers follow); u32 at 8, 12, 16: loaded sections, the most
  splats and the loaded splats; u16 at 20: the compression level (0, 1 or 2); float32 at 24:
  the scene centre (x y z); float32 at 36 and 40: the range of the 8-bit SH coefficients of
  level 2 (0 means the default, -1.5 and 1.5).
- One 1024-byte header per section: u32 at 0 and 4: the section's loaded and most splats; u32
  at 8: splats per full bucket; u32 at 12: buckets; float32 at 16: the bucket block size;
  u16 at 20: bytes per bucket record (12: a float32 centre); u32 at 24: the position
  quantisation range (0: 32767); u32 at 28: the section's bytes; u32 at 32 and 36: full and
  partially filled buckets; u16 at 40: the SH degree (0-3).
- Each section's data, in order after all section headers: the partially filled buckets'
  lengths (u32 each), the bucket centres, then the splats (``most splats`` records). Splats
  fill the full buckets first, then the partial ones in order.
- A splat record: position, scale (linear), rotation (w x y z), colour and opacity (u8 RGBA:
  the viewer draws byte / 255), SH rest. Level 0: float32 throughout. Levels 1 and 2: the
  position as u16 offsets from the bucket centre, ``(q - range) * block / 2 / range``; scale,
  rotation as float16; SH float16 (level 1) or u8 over the header's range (level 2).
  The SH rest is band by band (9, 15, 21 values), each band channel by channel.

Axes are PLY's (the converter writes the PLY's values as they are). Decoding: colour
``(c / 255 - 0.5) / SH_C0``; opacity the logit of a / 255, byte 0 alpha 0 (-inf), 255 alpha 1
(+inf); a scale of 0 or below (float16 underflow) becomes log scale -10, as splat-transform
reads it. Degree 3 (45 SH values a splat): the library 0.4.7 never writes it (its PLY reader
stops at degree 2); it is read in the layout above, as splat-transform reads it.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..model import PointModel
from .splat_model import to_model
from .splats import SplatFields, alpha_logit, color_to_dc, read_bytes

HEADER_BYTES = 4096
SECTION_BYTES = 1024
MAIN = struct.Struct("<BBxxIIIIH2x3f2f")
SECTION = struct.Struct("<IIIIfH2xIIIIH")
#: per compression level: the dtype of position, scale and rotation, of the SH values, and the
#: default position quantisation range
LEVELS = {0: ("<f4", "<f4", 1), 1: ("<u2", "<f2", 32767), 2: ("<u2", "u1", 32767)}
SH_VALUES = {0: 0, 1: 9, 2: 24, 3: 45}
BAND_SIZES = (3, 5, 7)
SH_RANGE = 1.5
ZERO_SCALE_LOG = -10.0
#: bytes a decoded splat needs at most per byte of its record (float32 fields from float16/u8)
DECODE_GROWTH = 4


def _record(level: int, degree: int) -> np.dtype:
    base, sh, _ = LEVELS[level]
    scale = "<f4" if level == 0 else "<f2"
    fields = [("center", base, 3), ("scale", scale, 3), ("rot", scale, 4), ("rgba", "u1", 4)]
    if SH_VALUES[degree]:
        fields.append(("sh", sh, SH_VALUES[degree]))
    return np.dtype(fields)


def parse_main(path: str | Path, head: bytes, size: int) -> dict:
    """The main header, its counts checked against the file's size."""
    if size < HEADER_BYTES or len(head) < MAIN.size:
        raise FormatError(f"{path}: {size:,} bytes is too small for a .ksplat file (its header "
                          f"alone is {HEADER_BYTES} bytes)")
    (major, minor, sections, loaded_sections, most, count, level, cx, cy, cz,
     sh_min, sh_max) = MAIN.unpack_from(head)
    if major != 0 or minor < 1:
        raise FormatError(f"{path}: .ksplat version {major}.{minor} is not supported (0.1 and "
                          "later 0.x)")
    if level not in LEVELS:
        raise FormatError(f"{path}: .ksplat compression level {level} is not 0, 1 or 2")
    if sections == 0 or count == 0:
        raise FormatError(f"{path}: the file holds no splats")
    if HEADER_BYTES + sections * SECTION_BYTES > size:
        raise FormatError(f"{path}: .ksplat header declares {sections:,} sections; their "
                          f"headers alone need more than the file's {size:,} bytes")
    smallest = _record(level, 0).itemsize
    if HEADER_BYTES + sections * SECTION_BYTES + count * smallest > size:
        raise FormatError(f"{path}: .ksplat header declares {count:,} splats; at least "
                          f"{count * smallest:,} bytes of splats, more than the file's "
                          f"{size:,} bytes hold")
    if count > most:
        raise FormatError(f"{path}: .ksplat header declares {count:,} loaded splats of at most "
                          f"{most:,}")
    return {"sections": sections, "count": count, "level": level,
            "sh_range": (sh_min or -SH_RANGE, sh_max or SH_RANGE),
            "scene_center": (cx, cy, cz)}


def _sections(path: str | Path, data: bytes | memoryview, main: dict, size: int) -> list[dict]:
    """Every section's header and byte offsets, checked to lie inside the file."""
    level = main["level"]
    at = HEADER_BYTES + main["sections"] * SECTION_BYTES
    out, total = [], 0
    for i in range(main["sections"]):
        (count, most, bucket_size, buckets, block, bucket_bytes, q_range, _, full, partial,
         degree) = SECTION.unpack_from(data, HEADER_BYTES + i * SECTION_BYTES)
        where = f"{path}: .ksplat section {i}"
        if degree not in SH_VALUES:
            raise FormatError(f"{where}: SH degree {degree} is not 0-3")
        if count > most:
            raise FormatError(f"{where} declares {count:,} loaded splats of at most {most:,}")
        record = _record(level, degree)
        q_range = q_range or LEVELS[level][2]
        if level == 0:
            bucket_bytes = buckets = partial = full = 0
        elif bucket_bytes != 12 or full + partial > buckets or \
                (count and (not np.isfinite(block) or block <= 0)) or \
                full * bucket_size > most:
            raise FormatError(f"{where}: bucket layout is inconsistent ({buckets:,} buckets of "
                              f"{bucket_bytes} bytes, {full:,} full of {bucket_size:,} splats, "
                              f"{partial:,} partial, block size {block})")
        need = partial * 4 + buckets * bucket_bytes + most * record.itemsize
        if at + need > size:
            raise FormatError(f"{where} needs {need:,} bytes at offset {at:,}, past the end of "
                              f"the file ({size:,} bytes)")
        out.append({"count": count, "bucket_size": bucket_size, "buckets": buckets,
                    "block": block, "q_range": q_range, "full": full, "partial": partial,
                    "degree": degree, "record": record, "lengths_at": at,
                    "centers_at": at + partial * 4,
                    "data_at": at + partial * 4 + buckets * bucket_bytes})
        at += need
        total += count
    if total != main["count"]:
        raise FormatError(f"{path}: .ksplat sections hold {total:,} splats; the header "
                          f"declares {main['count']:,}")
    return out


def _bucket_of(path: str | Path, data, s: dict) -> np.ndarray:
    """The bucket index of each of the section's splats."""
    n, size, full = s["count"], s["bucket_size"], s["full"]
    lengths = np.frombuffer(data, "<u4", s["partial"], s["lengths_at"]).astype(np.int64)
    in_full = min(n, full * size)
    if in_full + int(lengths.sum()) < n:
        raise FormatError(f"{path}: .ksplat buckets hold {in_full + int(lengths.sum()):,} "
                          f"splats of the section's {n:,}")
    # the partial buckets' lengths are clipped to the splats left (a length may declare far
    # more splats than the section holds: never expand what the file does not hold)
    ends = np.minimum(np.cumsum(lengths), n - in_full)
    first = np.arange(in_full) // max(size, 1)
    rest = np.repeat(np.arange(full, full + len(lengths)), np.diff(ends, prepend=0))
    return np.concatenate([first, rest])


def _decode_section(path: str | Path, data, main: dict, s: dict, degree: int) -> SplatFields:
    n, level = s["count"], main["level"]
    rec = np.frombuffer(data, s["record"], n, s["data_at"])
    if level == 0:
        positions = rec["center"].astype(np.float64)
    else:
        centers = np.frombuffer(data, "<f4", 3 * s["buckets"], s["centers_at"])
        centers = centers.reshape(-1, 3).astype(np.float64)
        step = float(s["block"]) / 2.0 / s["q_range"]
        positions = (rec["center"].astype(np.float64) - s["q_range"]) * step + \
            centers[_bucket_of(path, data, s)]
    scale = rec["scale"].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale_log = np.where(scale > 0, np.log(np.where(scale > 0, scale, 1.0)), ZERO_SCALE_LOG)
    scale_log = np.where(np.isnan(scale), np.nan, scale_log)
    rgba = rec["rgba"].astype(np.float64) / 255
    alpha = rgba[:, 3]
    opacity = alpha_logit(alpha)
    sh = np.zeros((n, 3, sum(BAND_SIZES[:degree])), np.float32)
    if s["degree"]:
        values = rec["sh"].astype(np.float64)
        if level == 2:
            lo, hi = main["sh_range"]
            values = lo + values / 255 * (hi - lo)
        at = col = 0
        for band in BAND_SIZES[:s["degree"]]:
            sh[:, :, col:col + band] = values[:, at:at + 3 * band].reshape(n, 3, band)
            at, col = at + 3 * band, col + band
    return SplatFields(positions=positions, scale_log=scale_log.astype(np.float32),
                       rotation=rec["rot"].astype(np.float32),
                       opacity=opacity.astype(np.float32),
                       sh_dc=color_to_dc(rgba[:, :3]).astype(np.float32), sh_rest=sh)


def decode(data: bytes, path: str | Path) -> SplatFields:
    """The splats of a whole .ksplat file, section after section."""
    main = parse_main(path, data, len(data))
    sections = _sections(path, data, main, len(data))
    degree = max(s["degree"] for s in sections if s["count"]) if main["count"] else 0
    parts = [_decode_section(path, data, main, s, degree) for s in sections if s["count"]]
    return SplatFields(*(np.concatenate([getattr(p, name) for p in parts]) for name in
                         ("positions", "scale_log", "rotation", "opacity", "sh_dc", "sh_rest")))


def read_info(path: str | Path) -> dict:
    """The header's fields (``info``): version, compression level, sections, SH degree."""
    from .regular import open_regular

    with open_regular(path) as f:
        size = f.seek(0, 2)
        f.seek(0)
        head = f.read(HEADER_BYTES)
        main = parse_main(path, head, size)
        f.seek(HEADER_BYTES)
        headers = f.read(main["sections"] * SECTION_BYTES)
    buf = head + headers
    degrees = [SECTION.unpack_from(buf, HEADER_BYTES + i * SECTION_BYTES)[-1]
               for i in range(main["sections"])]
    return {**main, "version": f"{head[0]}.{head[1]}", "sh_degree": max(degrees)}


def read_model(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    fields = decode(read_bytes(path), path)
    return to_model(fields, path, ["read from a .ksplat file by splatdeform"],
                    drop_nonfinite=drop_nonfinite)


def write_model(model: PointModel, path: Path, stream) -> None:
    raise InputError(f"{path}: .ksplat is read only here; write .splat, .spz, .sog, "
                     ".compressed.ply or .ply (the GaussianSplats3D viewer reads them)")


__all__ = ["decode", "read_info", "read_model", "parse_main"]
