"""PCD (Point Cloud Library) files, read and written by this module, every field kept.

Header lines (``#`` comments allowed): VERSION, FIELDS, SIZE, TYPE (I, U, F), COUNT, WIDTH,
HEIGHT, VIEWPOINT, POINTS, DATA (``ascii``, ``binary`` or ``binary_compressed``). The header's
fields are validated against each other and against the file size before anything is allocated.
Bodies: ``ascii`` rows of whitespace-separated values (parsed in chunks); ``binary`` packed rows
(little-endian); ``binary_compressed``: uint32 compressed size, uint32 raw size, then an LZF
block holding the data column by column (each field's values for every point in turn).

A save to ``.pcd`` writes the same fields, types, counts and DATA encoding as the input, with the
model's positions (and normals, when the file has ``normal_x..z``) written in; ascii values that
did not change keep their original text. Packed ``rgb``/``rgba`` floats are kept as raw bits; a
``TYPE F`` packed colour written as ascii text is the float whose bits it is (what Open3D and
pypcd4 read back as the same colour), or, where those bits are a NaN (an ``rgba`` with a high
alpha byte), the field is declared ``TYPE U`` and its bits written as an integer.

Organized clouds (HEIGHT > 1: RGB-D and structured-light frames) keep their grid. A grid cell
whose x, y or z is not finite is a hole, not a point: the model holds the finite cells only
(``PcdSource.finite``, the (WIDTH*HEIGHT,) mask of the cells that are its points, in grid
order), so a hole is never deformed, selected or rendered; the source keeps every cell, and a
save writes the model's points back into their cells, the holes as they were (NaN, with every
other field), WIDTH and HEIGHT kept. ``--drop-nonfinite`` has nothing to drop there.
"""

from __future__ import annotations

import io
import os
import re
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..model import PlyElementData, PlyProperty, PlySource, PointModel, classify
from .checks import check_fits, nonfinite_points
from .inflate import check_declared
from .ply_format import shortest_text
from .regular import open_regular

ENCODINGS = ("ascii", "binary", "binary_compressed")
_ENCODING: ContextVar[str | None] = ContextVar("pcd_encoding", default=None)
TYPE_SIZES = {"I": (1, 2, 4, 8), "U": (1, 2, 4, 8), "F": (4, 8)}
MAX_HEADER_LINES = 64
HEAD_BYTES = 2**20   # the header must end within the file's first MiB
ASCII_CHUNK_ROWS = 200_000
#: rows per block when records and float64 columns are filled (a block's rows stay in the cache)
FILL_ROWS = 1 << 16
PLY_TYPES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
             "u4": "uint", "f4": "float", "f8": "double", "i8": "double", "u8": "double"}


@dataclass
class PcdSource:
    """Everything a PCD file held. header: (key, value text) pairs in file order (comments as
    ('#', text)); fields/sizes/types/counts: the field table; data: (N,) structured array with
    one column per field (a COUNT > 1 field is a sub-array); encoding: the DATA line;
    ascii_text: for ascii files, (N, columns) the original value texts (bytes), else None.
    finite: for an organized cloud with holes, the (N,) bool mask of the cells that are the
    model's points (None: every cell is); ``rows`` are those cells' records."""

    header: list[tuple[str, str]]
    fields: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    width: int
    height: int
    encoding: str
    data: np.ndarray
    ascii_text: np.ndarray | None = None
    obj_info: list[str] = field(default_factory=list)
    text: bool = False
    byte_order: str = "<"
    finite: np.ndarray | None = None

    @property
    def rows(self) -> np.ndarray:
        """The records of the model's points: every cell's, or the finite cells' of an
        organized cloud with holes."""
        return self.data if self.finite is None else self.data[self.finite]

    @property
    def organized(self) -> str:
        """'640x480 with 182,292 finite' for an organized cloud, else ''."""
        if self.height <= 1:
            return ""
        n = len(self.data) if self.finite is None else int(self.finite.sum())
        return f"{self.width}x{self.height} with {n:,} finite"

    @property
    def comments(self) -> list[str]:
        grid = [f"organized {self.organized} (holes kept in place)"] if self.organized else []
        return [f"PCD {dict(self.header).get('VERSION', '')} DATA {self.encoding}", *grid,
                *(v for k, v in self.header if k == "#")]

    def element(self, name: str) -> PlyElementData | None:
        return self.elements[0] if name == "vertex" else None

    @property
    def elements(self) -> list[PlyElementData]:
        """The fields as one PLY-like vertex element (a COUNT > 1 field as name_0 ..)."""
        columns = []
        rows = self.rows
        for name, count in zip(self.fields, self.counts, strict=True):
            col = rows[name]
            if count == 1:
                columns.append((name, col))
            else:
                columns += [(f"{name}_{i}", col[:, i]) for i in range(count)]
        data = np.empty(len(rows), dtype=[(n, c.dtype) for n, c in columns])
        props = []
        for n, c in columns:
            data[n] = c
            props.append(PlyProperty(n, c.dtype.str[1:], PLY_TYPES[c.dtype.str[1:]]))
        return [PlyElementData("vertex", props, data)]


def _dtype(src_fields, sizes, types, counts) -> np.dtype:
    parts = []
    for name, size, kind, count in zip(src_fields, sizes, types, counts, strict=True):
        code = {"I": "i", "U": "u", "F": "f"}[kind] + str(size)
        parts.append((name, "<" + code) if count == 1 else (name, "<" + code, (count,)))
    return np.dtype(parts)


def _ints(path, key: str, words: list[str], low: int = 0) -> list[int]:
    try:
        values = [int(w) for w in words]
    except ValueError:
        raise FormatError(f"{path}: PCD {key} must be integers, got {' '.join(words)!r}") \
            from None
    if any(v < low for v in values):
        raise FormatError(f"{path}: PCD {key} values must be >= {low}")
    return values


def parse_header(path: str | Path, raw: bytes, size: int | None = None) -> tuple[PcdSource, int]:
    """(source without data, body offset); every field validated, one line per fault.
    ``raw``: the whole file, or its first bytes (at least the header, up to
    :data:`HEAD_BYTES`) with ``size`` the file's size: the declared points are checked against
    the body that size leaves (binary_compressed: against the block's own size fields when
    ``raw`` holds them)."""
    header: list[tuple[str, str]] = []
    values: dict[str, list[str]] = {}
    at = 0
    file_size = len(raw) if size is None else size
    for _ in range(MAX_HEADER_LINES + 200):
        end = raw.find(b"\n", at, HEAD_BYTES)
        if end < 0:
            raise FormatError(f"{path}: PCD header has no DATA line"
                              + (f" in the first {HEAD_BYTES:,} bytes" if file_size > HEAD_BYTES
                                 else ""))
        try:
            line = raw[at:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise FormatError(f"{path}: PCD header is not ASCII text") from None
        at = end + 1
        if not line:
            continue
        if line.startswith("#"):
            header.append(("#", line[1:].strip()))
            continue
        key, *words = line.split()
        if key not in ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT",
                       "VIEWPOINT", "POINTS", "DATA"):
            raise FormatError(f"{path}: unknown PCD header line {line[:60]!r}")
        if key in values:
            raise FormatError(f"{path}: PCD header line {key} appears twice")
        values[key] = words
        header.append((key, " ".join(words)))
        if key == "DATA":
            break
    else:
        raise FormatError(f"{path}: PCD header is too long")
    missing = [k for k in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT", "POINTS", "DATA")
               if k not in values]
    if missing:
        raise FormatError(f"{path}: PCD header lacks {', '.join(missing)}")
    names = values["FIELDS"]
    if not names or len(set(names)) != len(names) \
            or not all(re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", n) for n in names):
        raise FormatError(f"{path}: PCD FIELDS must be distinct names, got "
                          f"{' '.join(names)[:80]!r}")
    n_fields = len(names)
    sizes = _ints(path, "SIZE", values["SIZE"], 1)
    types = values["TYPE"]
    counts = _ints(path, "COUNT", values.get("COUNT", ["1"] * n_fields), 1)
    for key, got in (("SIZE", sizes), ("TYPE", types), ("COUNT", counts)):
        if len(got) != n_fields:
            raise FormatError(f"{path}: PCD {key} has {len(got)} entries for {n_fields} FIELDS")
    for name, size, kind in zip(names, sizes, types, strict=True):
        if kind not in TYPE_SIZES or size not in TYPE_SIZES[kind]:
            raise FormatError(f"{path}: PCD field {name}: TYPE {kind} SIZE {size} is not valid "
                              "(I/U with 1, 2, 4 or 8 bytes; F with 4 or 8)")
    if not all(n in names for n in "xyz"):
        raise FormatError(f"{path}: PCD FIELDS lack x, y or z")
    width, = _ints(path, "WIDTH", values["WIDTH"][:1] or ["?"])
    height, = _ints(path, "HEIGHT", values["HEIGHT"][:1] or ["?"])
    points, = _ints(path, "POINTS", values["POINTS"][:1] or ["?"])
    if width * height != points:
        raise FormatError(f"{path}: PCD WIDTH {width} x HEIGHT {height} != POINTS {points}")
    if points == 0:
        raise FormatError(f"{path}: PCD file has no points")
    if "VIEWPOINT" in values:
        try:
            vp = [float(v) for v in values["VIEWPOINT"]]
        except ValueError:
            vp = []
        if len(vp) != 7 or not np.isfinite(vp).all():
            raise FormatError(f"{path}: PCD VIEWPOINT must be 7 finite numbers")
    encoding = values["DATA"][0] if len(values["DATA"]) == 1 else ""
    if encoding not in ENCODINGS:
        raise FormatError(f"{path}: PCD DATA {' '.join(values['DATA'])!r}; expected one of "
                          f"{', '.join(ENCODINGS)}")
    dtype = _dtype(names, sizes, types, counts)
    body = file_size - at
    need = {"binary": points * dtype.itemsize, "binary_compressed": 8,
            "ascii": points * 2 * sum(counts) - 1}[encoding]
    if body < need:
        raise FormatError(f"{path}: PCD header declares {points:,} points ({need:,} bytes at "
                          f"least for DATA {encoding}); the body has {body:,}")
    if encoding == "binary_compressed" and len(raw) >= at + 8:
        _check_block(path, raw, at, points, dtype.itemsize, file_size)
    source = PcdSource(header=header, fields=names, sizes=sizes, types=types, counts=counts,
                       width=width, height=height, encoding=encoding,
                       data=np.empty(0, dtype=dtype))
    return source, at


def _check_block(path, raw: bytes, at: int, points: int, itemsize: int, size: int) -> int:
    """The binary_compressed block's sizes (uint32 compressed, uint32 raw) against the header
    and the file: the raw size must be POINTS x the record, the block within the file.
    Returns the compressed size."""
    packed, raw_size = struct.unpack_from("<II", raw, at)
    if raw_size != points * itemsize:
        raise FormatError(f"{path}: PCD binary_compressed raw size {raw_size:,} != POINTS "
                          f"{points:,} x {itemsize} bytes")
    if at + 8 + packed > size:
        raise FormatError(f"{path}: PCD binary_compressed block of {packed:,} bytes runs "
                          "past the end of the file")
    check_lzf_sizes(path, packed, raw_size)
    return packed


def read_header(path: str | Path) -> tuple[PcdSource, int, int]:
    """(source without data, body offset, file size) of the PCD file at ``path`` from its
    first bytes, validated like :func:`read_source` validates it (the declared POINTS against
    the file size, for every DATA encoding), through the one opener (no FIFO or device)."""
    path = Path(path)
    with open_regular(path) as fh:
        size = os.fstat(fh.fileno()).st_size
        head = fh.read(HEAD_BYTES + 8)
    source, at = parse_header(path, head, size)
    return source, at, size


# ---- LZF (the binary_compressed block) ------------------------------------------------------

#: the most an LZF stream can expand: a 3-byte back reference copies at most 264 bytes (88:1);
#: literals and shorter references expand less
LZF_MAX_RATIO = 88


def check_lzf_sizes(path, packed: int, raw_size: int) -> None:
    """Refuse a binary_compressed block whose declared raw size its ``packed`` bytes cannot
    expand to (:data:`LZF_MAX_RATIO`), or whose decoded data (the raw block and the decoded
    columns: twice the raw size) is more than the machine's memory, before anything is
    allocated; one line naming the file and what it declared."""
    if raw_size > LZF_MAX_RATIO * packed:
        raise FormatError(f"{path}: PCD binary_compressed block declares {raw_size:,} raw bytes "
                          f"from {packed:,} compressed bytes; LZF expands at most "
                          f"{LZF_MAX_RATIO}x")
    check_declared(path, f"PCD binary_compressed block ({raw_size:,} raw bytes declared)",
                   2 * raw_size)


def lzf_decompress(path, data: bytes | memoryview, size: int) -> bytes:
    """The ``size`` bytes the LZF block ``data`` decodes to (the compiled liblzf through
    python-lzf, with at most ``size`` bytes of output): one FormatError line naming ``path``
    when the block is corrupt or decodes to another size. The caller checks ``size`` against
    the block and the memory first (:func:`check_lzf_sizes`)."""
    import lzf

    if size == 0:
        if len(data):
            raise FormatError(f"{path}: PCD binary_compressed block holds data past its "
                              "declared 0 raw bytes")
        return b""
    try:
        out = lzf.decompress(bytes(data), size)
    except ValueError:
        raise FormatError(f"{path}: PCD binary_compressed block is corrupt") from None
    if out is None:
        raise FormatError(f"{path}: PCD binary_compressed block is corrupt (it does not "
                          f"decode within the {size:,} bytes its header says)")
    if len(out) != size:
        raise FormatError(f"{path}: PCD binary_compressed block decodes to {len(out):,} bytes, "
                          f"its header says {size:,}")
    return out


#: liblzf's own ``lzf_decompress`` in python-lzf's compiled module, called through ctypes
#: (:func:`lzf_decode`); [None] where the module does not export it
_DIRECT_LZF: list = []


def _direct_lzf():
    if not _DIRECT_LZF:
        import ctypes

        import lzf

        try:
            fn = ctypes.CDLL(lzf.__file__, use_errno=True).lzf_decompress
            fn.restype = ctypes.c_uint
            fn.argtypes = [ctypes.c_void_p, ctypes.c_uint, ctypes.c_void_p, ctypes.c_uint]
        except (OSError, AttributeError, TypeError):   # not a shared object, or no such symbol
            fn = None
        _DIRECT_LZF.append(fn)
    return _DIRECT_LZF[0]


def lzf_decode(path, data: bytes | np.ndarray, size: int) -> np.ndarray:
    """(size,) uint8: what :func:`lzf_decompress` returns, with its checks and error lines,
    decoded by the same compiled liblzf straight into the array: python-lzf's module exports
    liblzf's ``lzf_decompress``, called here through ctypes with python-lzf's arguments (room
    for ``size`` bytes), which spares python-lzf's copy of the output and lets go of the
    GIL; python-lzf's ``decompress`` where the module does not export it."""
    direct = _direct_lzf()
    if direct is None or size == 0:
        return np.frombuffer(lzf_decompress(path, data, size), dtype=np.uint8)
    import ctypes
    import errno

    out = np.empty(size, dtype=np.uint8)
    ctypes.set_errno(0)
    block = np.frombuffer(data, dtype=np.uint8)   # no copy (bytes, or _read's array)
    got = direct(block.ctypes.data, len(block), out.ctypes.data, size)
    if got == 0 and ctypes.get_errno() == errno.EINVAL:
        raise FormatError(f"{path}: PCD binary_compressed block is corrupt")
    if got == 0:
        raise FormatError(f"{path}: PCD binary_compressed block is corrupt (it does not "
                          f"decode within the {size:,} bytes its header says)")
    if got != size:
        raise FormatError(f"{path}: PCD binary_compressed block decodes to {got:,} bytes, "
                          f"its header says {size:,}")
    return out


def lzf_compress(data: bytes | memoryview) -> bytes:
    """``data`` as an LZF stream (liblzf's format and compressor, which PCL's binary_compressed
    uses), through python-lzf; incompressible data costs at most a byte in 32 more."""
    import lzf

    data = bytes(data)
    if not data:
        return b""
    out = lzf.compress(data, len(data) + len(data) // 16 + 64)
    if out is None:  # pragma: no cover - liblzf's worst case is n + n/32 + 1
        raise FormatError("LZF compression produced more than its worst case")
    return out


# ---- reading --------------------------------------------------------------------------------

def _parse_ascii(path, body: bytes, source: PcdSource, points: int):
    dtype = source.data.dtype
    columns = sum(source.counts)
    rows = body.split(b"\n", points)
    lines = [r for r in rows[:points] if r.strip()]
    if len(lines) < points or (len(rows) > points and rows[points].strip()):
        got = len(lines)
        raise FormatError(f"{path}: PCD ascii body has {got:,} rows"
                          f"{'' if got < points else ' or more'}; the header says POINTS "
                          f"{points:,}" if got < points else
                          f"{path}: PCD ascii body has more rows than POINTS {points:,}")
    texts = np.empty((points, columns), dtype=object)
    data = np.empty(points, dtype=dtype)
    flat_kinds = [(name, i) for name, c in zip(source.fields, source.counts, strict=True)
                  for i in range(c)]
    for start in range(0, points, ASCII_CHUNK_ROWS):
        chunk = lines[start:start + ASCII_CHUNK_ROWS]
        words = [ln.split() for ln in chunk]
        if any(len(w) != columns for w in words):
            bad = next(k for k, w in enumerate(words) if len(w) != columns)
            raise FormatError(f"{path}: PCD ascii row {start + bad} has {len(words[bad])} "
                              f"values; expected {columns}")
        block = np.array(words, dtype=object)
        texts[start:start + len(chunk)] = block
        for col, (name, i) in enumerate(flat_kinds):
            target = data[name][start:start + len(chunk)]
            kind = dtype[name].base.kind
            try:
                if kind == "f" and name in ("rgb", "rgba"):
                    vals = np.array([_packed_color(w) for w in block[:, col]], dtype=np.uint32)\
                        .view(np.float32)
                elif kind == "f":
                    vals = np.array(block[:, col].astype(str), dtype=np.float64)
                else:
                    vals = np.array(block[:, col].astype(str), dtype=np.int64)
            except ValueError:
                raise FormatError(f"{path}: PCD ascii field {name}: a value is not a "
                                  f"{'number' if kind == 'f' else 'integer'}") from None
            if target.ndim == 2:
                target[:, i] = vals
            else:
                target[:] = vals
    return data, texts


def _packed_color(word: bytes) -> int:
    """An ascii rgb value: PCL writes the packed float's bits as an unsigned integer (or as
    the float's own text): keep the 32 bits."""
    if re.fullmatch(rb"[0-9]+", word):
        return int(word) & 0xFFFFFFFF
    return int(np.array(float(word), dtype=np.float32).view(np.uint32))


def read_source(path: str | Path) -> tuple[PcdSource, int]:
    """(source with its records, body offset) of the PCD file at ``path``."""
    source, at, _ = _read(path)
    return source, at


def _read(path: str | Path, groups: tuple[tuple[str, ...], ...] = ()
          ) -> tuple[PcdSource, int, list[tuple[np.ndarray | None, bool]]]:
    """:func:`read_source`'s (source, body offset) and, per group of field names in
    ``groups``, (their (N, len(group)) float64 values, whether every one is finite), taken
    from a compressed block's columns as the records are filled ((None, False) for the other
    encodings, or where a field is missing or has COUNT > 1: :func:`_columns` of the records
    then). The header is parsed from the file's first bytes and checked against its size; a
    binary or compressed body is read alone (the compressed block straight into the buffer
    the decoder reads, no copy of the file)."""
    path = Path(path)
    none: list[tuple[np.ndarray | None, bool]] = [(None, False)] * len(groups)
    with open_regular(path) as fh:
        size = os.fstat(fh.fileno()).st_size
        head = fh.read(HEAD_BYTES + 8)
        source, at = parse_header(path, head, size)
        points = source.width * source.height
        dtype = source.data.dtype
        if source.encoding == "binary_compressed":
            packed = _check_block(path, head, at, points, dtype.itemsize, size)
            fh.seek(at + 8)
            # the block is read into the records' memory when it fits there (the records are
            # filled only after it is decoded): one allocation of the file's size less
            data = np.empty(points, dtype=dtype)
            flat = data.view(np.uint8)
            block = flat[:packed] if packed <= flat.size else np.empty(packed, np.uint8)
            block = block[:fh.readinto(block)]
        elif source.encoding == "binary":
            fh.seek(at)
            data = np.fromfile(fh, dtype=dtype, count=points)
            if len(data) != points:   # the file shrank after its size was read
                raise FormatError(f"{path}: PCD binary body ends after {len(data):,} of "
                                  f"{points:,} points")
            return replace(source, data=data), at, none
        else:
            fh.seek(at)
            body = fh.read()
    if source.encoding == "ascii":
        data, texts = _parse_ascii(path, body, source, points)
        return replace(source, data=data, ascii_text=texts), at, none
    raw = lzf_decode(path, block, points * dtype.itemsize)
    del block
    columns, offset = {}, 0
    for name in source.fields:
        sub = dtype[name]
        columns[name] = np.frombuffer(raw, dtype=sub.base, count=points * (
            sub.itemsize // sub.base.itemsize), offset=offset).reshape(data[name].shape)
        offset += sub.itemsize * points
    outs = [np.empty((points, len(g)), dtype=np.float64)
            if all(n in columns and not dtype[n].shape for n in g) else None for g in groups]
    finite = [out is not None for out in outs]
    for start in range(0, points, FILL_ROWS):   # each block's records written from the cache
        stop = start + FILL_ROWS
        for name, column in columns.items():
            data[name][start:stop] = column[start:stop]
        for k, (out, group) in enumerate(zip(outs, groups, strict=True)):
            for i, name in enumerate(group if out is not None else ()):
                out[start:stop, i] = columns[name][start:stop]
            if finite[k]:
                finite[k] = bool(np.isfinite(out[start:stop]).all())
    return replace(source, data=data), at, list(zip(outs, finite, strict=True))


def _columns(data: np.ndarray, names: tuple[str, ...]) -> np.ndarray | None:
    """(N, len(names)) float64 of those fields of the records ``data`` (None when one is
    missing), filled block by block (no float64 temporaries; each block's rows read once)."""
    if not all(n in (data.dtype.names or ()) for n in names):
        return None
    if any(data.dtype[n].shape for n in names):   # a COUNT > 1 field: (N, 3, COUNT) as before
        return np.stack([data[n].astype(np.float64) for n in names], axis=1)
    out = np.empty((len(data), len(names)), dtype=np.float64)
    for start in range(0, len(data), FILL_ROWS):
        for i, n in enumerate(names):
            out[start:start + FILL_ROWS, i] = data[n][start:start + FILL_ROWS]
    return out


def _colors(data: np.ndarray) -> np.ndarray | None:
    name = next((n for n in ("rgb", "rgba") if n in (data.dtype.names or ())), None)
    if name is None or data[name].ndim != 1:
        return None
    bits = data[name].view(np.uint32) if data[name].dtype.itemsize == 4 else \
        data[name].astype(np.uint32)
    return np.stack([(bits >> 16) & 255, (bits >> 8) & 255, bits & 255], axis=1).astype(np.uint8)


def organized_holes(path, source: PcdSource, positions: np.ndarray) -> PcdSource:
    """``source`` with its :attr:`~PcdSource.finite` mask when it is an organized cloud
    (HEIGHT > 1) with holes (cells whose x, y or z is not finite); positions (N, 3)."""
    if source.height <= 1:
        return source
    finite = np.isfinite(positions).all(axis=1)
    if finite.all():
        return source
    if not finite.any():
        raise FormatError(f"{path}: the organized PCD ({source.width}x{source.height}) has no "
                          "finite point")
    return replace(source, finite=finite)


def xyz_of(data: np.ndarray) -> np.ndarray:
    """(N, 3) float64 x y z of PCD records (N,)."""
    return _columns(data, ("x", "y", "z"))


def read_model(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    xyz, normal_names = ("x", "y", "z"), ("normal_x", "normal_y", "normal_z")
    source, _, ((positions, finite), (normals, normals_finite)) = _read(path,
                                                                        (xyz, normal_names))
    data = source.data
    if positions is None:
        positions = _columns(data, xyz)
        finite = bool(np.isfinite(positions).all())
    source = organized_holes(path, source, positions)
    if source.finite is not None:   # the finite cells
        data, positions, normals, finite = source.rows, positions[source.finite], None, True
    if not finite:   # the usual case has no per-point mask
        bad = nonfinite_points(path, positions, drop_nonfinite)
        keep = ~bad
        source = replace(source, data=data[keep], width=int(keep.sum()), height=1,
                         ascii_text=None if source.ascii_text is None
                         else source.ascii_text[keep])
        data, positions, normals = source.data, positions[keep], None
    if normals is None:   # not from a compressed block, or points dropped: from the records
        normals = _columns(data, normal_names)
        normals_finite = normals is not None and bool(np.isfinite(normals).all())
    if not normals_finite:
        normals = None
    colors = _colors(data)
    kind = classify(has_faces=False, has_normals=normals is not None, has_radius=False,
                    has_axes=False, has_gaussians=False)
    return PointModel(positions=positions, normals=normals, colors=colors, kind=kind,
                      source=source, path=str(path))


# ---- writing --------------------------------------------------------------------------------

@contextmanager
def data_encoding(name: str | None) -> Iterator[None]:
    """PCD writes inside the block use the DATA encoding ``name`` (one of :data:`ENCODINGS`;
    None: the input's own, ``binary`` for a model not read from PCD)."""
    if name is not None and name not in ENCODINGS:
        raise InputError(f"pcd encoding: expected one of {', '.join(ENCODINGS)}, got {name!r}")
    token = _ENCODING.set(name)
    try:
        yield
    finally:
        _ENCODING.reset(token)


def source_for_save(model: PointModel) -> PcdSource:
    """The model's PCD source with its positions (and normals) written in, or a new xyz
    (+ normals, rgb) source for a model not read from PCD; in the :func:`data_encoding` in
    force, else the input's."""
    source = _source_for_save(model)
    forced = _ENCODING.get()
    if forced is not None and forced != source.encoding:
        source = replace(source, encoding=forced, ascii_text=None)
    return source


def _source_for_save(model: PointModel) -> PcdSource:
    source = model.source if isinstance(model.source, PcdSource) else None
    if source is None:
        names = ["x", "y", "z"]
        cols = [model.positions[:, i] for i in range(3)]
        if model.normals is not None:
            names += ["normal_x", "normal_y", "normal_z"]
            cols += [model.normals[:, i] for i in range(3)]
        # float32 unless a value needs float64 (beyond float32's range: it would become inf)
        wide = {n for n, c in zip(names, cols, strict=True)
                if np.abs(c[np.isfinite(c)]).max(initial=0.0) > np.finfo(np.float32).max}
        data = np.empty(model.n_points, dtype=[(n, "<f8" if n in wide else "<f4") for n in names]
                        + ([("rgb", "<f4")] if model.colors is not None else []))
        for n, c in zip(names, cols, strict=True):
            data[n] = c
        if model.colors is not None:
            c = model.colors.astype(np.uint32)
            data["rgb"] = ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).view(np.float32)
        names = list(data.dtype.names)
        sizes = [data.dtype[n].itemsize for n in names]
        return PcdSource(header=[("#", "written by splatdeform")], fields=names,
                         sizes=sizes, types=["F"] * len(names),
                         counts=[1] * len(names), width=model.n_points, height=1,
                         encoding="binary", data=data)
    cells = None if source.finite is None else np.flatnonzero(source.finite)
    held = len(source.data) if cells is None else len(cells)
    if held != model.n_points:
        raise FormatError(f"model has {model.n_points} points but its PCD source "
                          f"{held}; cannot save it field by field")
    data = source.data.copy()
    texts = None if source.ascii_text is None else source.ascii_text.copy()
    updates = [("x", model.positions[:, 0]), ("y", model.positions[:, 1]),
               ("z", model.positions[:, 2])]
    if model.normals is not None and all(f"normal_{a}" in source.fields for a in "xyz"):
        updates += [(f"normal_{a}", model.normals[:, i]) for i, a in enumerate("xyz")]
    starts = np.cumsum([0, *source.counts])
    for name, values in updates:
        column = data[name]
        check_fits(f"PCD field {name}", values, column.dtype,
                   f"its TYPE {source.types[source.fields.index(name)]} SIZE "
                   f"{column.dtype.itemsize}:")
        new = values.astype(column.dtype)
        changed = new != (column if cells is None else column[cells])
        at = changed if cells is None else cells[changed]   # the cells (holes stay as read)
        column[at] = new[changed]
        if texts is not None and changed.any():
            col = starts[source.fields.index(name)]
            texts[at, col] = [t.encode() for t in shortest_text(new[changed],
                                                                column.dtype.str[1:])]
    return replace(source, data=data, ascii_text=texts)


def _header_bytes(source: PcdSource) -> bytes:
    points = len(source.data)
    width, height = (source.width, source.height) if source.width * source.height == points \
        else (points, 1)
    table = {"FIELDS": " ".join(source.fields), "SIZE": " ".join(map(str, source.sizes)),
             "TYPE": " ".join(source.types), "COUNT": " ".join(map(str, source.counts)),
             "WIDTH": str(width), "HEIGHT": str(height), "POINTS": str(points),
             "DATA": source.encoding}
    lines, seen = [], set()
    for key, value in source.header:
        if key == "#":
            lines.append(f"# {value}".rstrip())
            continue
        lines.append(f"{key} {table.get(key, value)}")
        seen.add(key)
    defaults = [("VERSION", "0.7"), ("FIELDS", None), ("SIZE", None), ("TYPE", None),
                ("COUNT", None), ("WIDTH", None), ("HEIGHT", None),
                ("VIEWPOINT", "0 0 0 1 0 0 0"), ("POINTS", None), ("DATA", None)]
    body = [ln for ln in lines if not ln.startswith("DATA ")]
    for key, value in defaults:
        if key not in seen and key != "DATA":
            body.append(f"{key} {table.get(key, value)}")
    body.append(f"DATA {source.encoding}")
    return ("\n".join(body) + "\n").encode("ascii")


def write_source(source: PcdSource, out) -> None:
    if source.encoding == "ascii" and source.ascii_text is None:
        source = _packed_colour_types(source)
    out.write(_header_bytes(source))
    data = source.data
    if source.encoding == "binary":
        out.write(data.astype(data.dtype.newbyteorder("<")).tobytes())
    elif source.encoding == "binary_compressed":
        raw = b"".join(np.ascontiguousarray(data[n]).tobytes() for n in source.fields)
        packed = lzf_compress(raw)
        out.write(struct.pack("<II", len(packed), len(raw)))
        out.write(packed)
    else:
        texts = source.ascii_text
        if texts is None:
            texts = _ascii_texts(source)
        buf = io.BytesIO()
        for start in range(0, len(texts), ASCII_CHUNK_ROWS):
            block = texts[start:start + ASCII_CHUNK_ROWS]
            buf.seek(0)
            buf.truncate()
            buf.write(b"\n".join(b" ".join(row) for row in block) + b"\n")
            out.write(buf.getvalue())


def _is_packed_colour(name: str, column: np.ndarray) -> bool:
    return name in ("rgb", "rgba") and column.dtype.base == np.float32


def _packed_colour_types(source: PcdSource) -> PcdSource:
    """``source`` with each packed-colour field whose bits include a NaN float (text cannot
    carry its bits) declared ``TYPE U`` for an ascii write; the others stay ``F``."""
    types = list(source.types)
    for k, name in enumerate(source.fields):
        column = source.data[name]
        if types[k] == "F" and _is_packed_colour(name, column) and np.isnan(column).any():
            types[k] = "U"
    return source if types == source.types else replace(source, types=types)


def _float_bits_texts(values: np.ndarray) -> list[bytes]:
    """Texts of float32 ``values`` (finite) that read back to the same bits, never a plain
    integer (which our reader, like PCL's ascii rgb, takes for the bits themselves)."""
    out = []
    for t in shortest_text(values, "f4"):
        if t.lstrip("-").isdigit():
            t += ".0"
        out.append(t.encode())
    return out


def _ascii_texts(source: PcdSource) -> np.ndarray:
    cols = []
    for name, kind in zip(source.fields, source.types, strict=True):
        column = source.data[name]
        column = column if column.ndim == 2 else column[:, None]
        for i in range(column.shape[1]):
            if _is_packed_colour(name, column) and kind == "U":
                cols.append([str(int(v)).encode() for v in column[:, i].view(np.uint32)])
            elif _is_packed_colour(name, column):
                cols.append(_float_bits_texts(column[:, i]))
            else:
                cols.append([t.encode() for t in shortest_text(column[:, i],
                                                               column.dtype.str[1:])])
    return np.array(cols, dtype=object).T if cols else np.empty((0, 0), dtype=object)


def write_model(model: PointModel, path: Path, stream) -> None:
    write_source(source_for_save(model), stream)


def ply_source_from_pcd(source: PcdSource) -> PlySource:
    """Every PCD field as a PLY vertex property (for PCD -> PLY conversion)."""
    return PlySource(elements=source.elements, comments=source.comments)
