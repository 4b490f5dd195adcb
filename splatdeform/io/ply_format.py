"""Raw PLY reading and writing: header, ascii and binary (little/big endian) bodies.

Why not plyfile's own reader/writer: it parses ascii rows and binary list rows in a Python loop
per row (seconds for a 100k-face mesh) and its errors do not name the file. This module parses the
header itself (errors name the file and line), reads bodies with numpy in bulk, and falls back to
a per-row loop only for variable-length lists. The result is a :class:`PlySource` that a save
writes back unchanged: same elements, property names, type spellings, order and comments.
"""

from __future__ import annotations

import array
import io
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..model import AsciiRows, PlyElementData, PlyProperty, PlySource
from .regular import check_regular

TYPE_CODES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
TYPE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
              "u4": "uint", "f4": "float", "f8": "double"}  # fmt: skip
FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
MAX_HEADER_BYTES = 1 << 20
ASCII_CHUNK_ROWS = 100_000  # ascii rows parsed (and written) per block: bounded token lists
MAX_COUNT_DIGITS = 15  # 1e15 rows: far beyond any file that fits on a disk


class PlyHeader:
    """A parsed PLY header: format, comments, elements (name, count, properties) and the
    header's size in bytes and lines."""

    def __init__(self) -> None:
        self.text = False
        self.byte_order = "<"
        self.comments: list[str] = []
        self.obj_info: list[str] = []
        self.elements: list[tuple[str, int, list[PlyProperty]]] = []
        self.size = 0  # bytes up to and including the end_header line
        self.lines = 0  # lines up to and including the end_header line


def _header_lines(path: Path, raw: bytes) -> tuple[list[bytes], int]:
    """The header lines before ``end_header`` and the body's byte offset.

    ``end_header`` must be a line of its own: a comment that mentions it does not end the header.
    """
    lines: list[bytes] = []
    pos = 0
    limit = min(len(raw), MAX_HEADER_BYTES)
    while pos < limit:
        newline = raw.find(b"\n", pos, limit)
        end = limit if newline < 0 else newline
        line = raw[pos:end]
        if line.strip() == b"end_header":
            return lines, len(raw) if newline < 0 else newline + 1
        lines.append(line)
        if newline < 0:
            break
        pos = newline + 1
    raise FormatError(f"{path}: malformed PLY header: no 'end_header' line"
                      + (f" in the first {MAX_HEADER_BYTES} bytes" if len(raw) > limit else ""))


def parse_header(path: Path, raw: bytes) -> PlyHeader:
    """The header at the start of ``raw`` (the file's first bytes, up to
    :data:`MAX_HEADER_BYTES` of header). ``path`` names the file in errors. Raises FormatError
    for a malformed header."""
    if not raw.startswith(b"ply"):
        raise FormatError(f"{path}: not a PLY file (it does not start with 'ply')")
    raw_lines, size = _header_lines(path, raw)
    header = PlyHeader()
    header.size = size
    header.lines = len(raw_lines) + 1
    seen_format = False
    names: set[str] = set()  # property names of the current element (linear duplicate check)
    for number, raw_line in enumerate(raw_lines[1:], start=2):
        try:
            line = raw_line.decode("ascii")
        except UnicodeDecodeError as exc:
            raise FormatError(f"{path}: malformed PLY header, line {number}: non-ASCII bytes") \
                from exc
        words = line.split()
        if not words:
            continue
        where = f"{path}: malformed PLY header, line {number} ({line.strip()[:80]!r})"
        key = words[0]
        if key == "format":
            if len(words) != 3 or words[1] not in FORMATS:
                raise FormatError(f"{where}: expected 'format ascii|binary_little_endian|"
                                  "binary_big_endian 1.0'")
            header.text = FORMATS[words[1]] is None
            header.byte_order = FORMATS[words[1]] or "<"
            seen_format = True
        elif key == "comment":
            header.comments.append(line.strip()[len("comment"):].strip())
        elif key == "obj_info":
            header.obj_info.append(line.strip()[len("obj_info"):].strip())
        elif key == "element":
            if len(words) != 3 or not (words[2].isascii() and words[2].isdigit()):
                raise FormatError(f"{where}: expected 'element <name> <count>'")
            if len(words[2].lstrip("0")) > MAX_COUNT_DIGITS:
                raise FormatError(f"{where}: element count {words[2][:20]}... is too large")
            _check_previous_element(path, header, number)
            if any(words[1] == el[0] for el in header.elements):
                raise FormatError(f"{where}: a second element '{words[1]}'; element names must "
                                  "be unique (readers would see only the first)")
            header.elements.append((words[1], int(words[2]), []))
            names = set()
        elif key == "property":
            if not header.elements:
                raise FormatError(f"{where}: property before any element")
            props = header.elements[-1][2]
            if len(words) == 5 and words[1] == "list":
                if words[2] not in TYPE_CODES or words[3] not in TYPE_CODES:
                    raise FormatError(f"{where}: unknown list type; expected one of "
                                      f"{', '.join(TYPE_CODES)}")
                if TYPE_CODES[words[2]][0] == "f":
                    raise FormatError(f"{where}: list length type must be an integer type")
                prop = PlyProperty(words[4], TYPE_CODES[words[3]], words[3], True,
                                   TYPE_CODES[words[2]], words[2])
            elif len(words) == 3 and words[1] in TYPE_CODES:
                prop = PlyProperty(words[2], TYPE_CODES[words[1]], words[1])
            else:
                raise FormatError(f"{where}: expected 'property <type> <name>' or "
                                  "'property list <count type> <type> <name>'")
            if prop.name in names:
                raise FormatError(f"{where}: duplicate property {prop.name!r}")
            names.add(prop.name)
            props.append(prop)
        else:
            raise FormatError(f"{where}: unknown keyword {key!r}")
    if not seen_format:
        raise FormatError(f"{path}: malformed PLY header: no 'format' line")
    _check_previous_element(path, header, header.lines)
    return header




def _check_previous_element(path: Path, header: PlyHeader, number: int) -> None:
    """An element with rows but no properties has nothing to read (and no size to bound)."""
    if header.elements and header.elements[-1][1] > 0 and not header.elements[-1][2]:
        name, count, _ = header.elements[-1]
        raise FormatError(f"{path}: malformed PLY header, before line {number}: element "
                          f"{name!r} declares {count} rows but no properties")


def _min_row_bytes(props: list[PlyProperty], text: bool) -> int:
    """The fewest bytes one row can take (lists empty): binary sizes, or ascii tokens of one
    character each followed by one separator."""
    if text:
        return 2 * len(props)
    return sum(np.dtype(p.len_dtype if p.is_list else p.dtype).itemsize for p in props)


def _check_declared_size(path: Path, header: PlyHeader, body_bytes: int) -> None:
    """Refuse a header whose element counts cannot fit in the file, before allocating anything."""
    needed = 0
    for name, count, props in header.elements:
        needed += count * _min_row_bytes(props, header.text)
        # an ascii body may lack the final newline: one byte of slack
        if needed > body_bytes + (1 if header.text else 0):
            raise FormatError(
                f"{path}: the header declares more data than the file holds: element '{name}' "
                f"({count} rows) needs at least {needed} body bytes up to its end, the body has "
                f"{body_bytes} (file cut short, or the header's count is wrong)")


def _object_dtype(props: list[PlyProperty], byte_order: str) -> np.dtype:
    return np.dtype([(p.name, object if p.is_list else byte_order + p.dtype) for p in props])


def _empty(props: list[PlyProperty], count: int, byte_order: str) -> np.ndarray:
    return np.empty(count, dtype=_object_dtype(props, byte_order))


def _packed_dtype(props: list[PlyProperty], lengths: dict[str, int], bo: str) -> np.dtype:
    """Record dtype of rows whose list properties all have fixed ``lengths`` (count + values)."""
    fields = []
    for p in props:
        if p.is_list:
            fields.append((p.name + "\nlen", bo + p.len_dtype))
            fields.append((p.name, bo + p.dtype, (lengths[p.name],)))
        else:
            fields.append((p.name, bo + p.dtype))
    return np.dtype(fields)


def _fixed_lists(values: np.ndarray) -> np.ndarray:
    """(R, L) values -> (R,) object column of 1-D rows. Empty rows all share one empty array
    (8 bytes a row instead of an array object each: a body of zero-length lists stays small)."""
    column = np.empty(values.shape[0], dtype=object)
    if values.shape[1] == 0:
        column.fill(np.empty(0, dtype=values.dtype))
    else:
        column[:] = list(np.ascontiguousarray(values))
    return column


def _ragged_lists(values: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """All rows' values (M,) in row order and each row's length (R,) -> (R,) object column
    (empty rows share one empty array, as in :func:`_fixed_lists`)."""
    column = np.empty(len(lengths), dtype=object)
    column.fill(np.empty(0, dtype=values.dtype))
    filled = lengths > 0
    if filled.any():
        pieces = np.empty(int(filled.sum()), dtype=object)
        pieces[:] = np.split(values, np.cumsum(lengths)[filled][:-1])
        column[filled] = pieces
    return column


def _split_lists(packed: np.ndarray, props: list[PlyProperty], byte_order: str) -> np.ndarray:
    """Packed fixed-length records -> the object-field layout."""
    out = _empty(props, packed.shape[0], byte_order)
    for p in props:
        if p.is_list:
            out[p.name] = _fixed_lists(packed[p.name])
        else:
            out[p.name] = packed[p.name]
    return out


def _read_binary_element(path: Path, buf: memoryview, offset: int, name: str, count: int,
                         props: list[PlyProperty], bo: str) -> tuple[np.ndarray, int]:
    total = len(buf)

    def truncated(needed: int, at: int = offset) -> FormatError:
        return FormatError(f"{path}: truncated binary body: element '{name}' needs at least "
                           f"{needed} more bytes, {max(total - at, 0)} left "
                           "(file cut short, or the header's count is wrong)")

    def negative(row: int, prop: PlyProperty, n: int) -> FormatError:
        return FormatError(f"{path}: malformed binary body: element '{name}' row {row}: list "
                           f"'{prop.name}' has a negative length ({n})")

    if not any(p.is_list for p in props):
        dtype = np.dtype([(p.name, bo + p.dtype) for p in props])
        if offset + dtype.itemsize * count > total:
            raise truncated(dtype.itemsize * count)
        data = np.frombuffer(buf, dtype=dtype, count=count, offset=offset)
        return data, offset + dtype.itemsize * count
    if count == 0:
        return _empty(props, 0, bo), offset
    # Fixed-length fast path: list lengths of the first row, checked on every row.
    lengths: dict[str, int] = {}
    pos = offset
    for p in props:
        if p.is_list:
            size = np.dtype(p.len_dtype).itemsize
            if pos + size > total:
                raise truncated(size)
            n = int(np.frombuffer(buf, dtype=bo + p.len_dtype, count=1, offset=pos)[0])
            if n < 0:
                raise negative(0, p, n)
            lengths[p.name] = n
            pos += size + n * np.dtype(p.dtype).itemsize
        else:
            pos += np.dtype(p.dtype).itemsize
    packed_dtype = _packed_dtype(props, lengths, bo)
    if offset + packed_dtype.itemsize * count <= total:
        packed = np.frombuffer(buf, dtype=packed_dtype, count=count, offset=offset)
        if all((packed[n + "\nlen"] == L).all() for n, L in lengths.items()):
            return _split_lists(packed, props, bo), offset + packed_dtype.itemsize * count
    # Variable-length lists: a plain-Python walk over the row layout finds where every value
    # sits (bounded: count * the smallest row fits the file, checked by _check_declared_size),
    # then numpy gathers each property for all rows at once.
    layout = [(p.is_list, np.dtype(p.len_dtype if p.is_list else p.dtype).itemsize,
               np.dtype(p.dtype).itemsize, p.is_list and p.len_dtype[0] == "i") for p in props]
    byteorder = "little" if bo == "<" else "big"
    # byte offset of each row's value(s), and list lengths (list properties only); typed
    # arrays hold 8 bytes a row where lists of Python ints would hold ~40
    starts = [array.array("q") for _ in props]
    lengths = [array.array("q") for _ in props]
    pos = offset
    for row in range(count):
        for i, (is_list, size, item, signed) in enumerate(layout):
            if pos + size > total:
                raise truncated(size, pos)
            if is_list:
                n = int.from_bytes(buf[pos:pos + size], byteorder, signed=signed)
                if n < 0:
                    raise negative(row, props[i], n)
                pos += size
                starts[i].append(pos)
                lengths[i].append(n)
                pos += n * item
                if pos > total:
                    raise truncated(n * item, pos - n * item)
            else:
                starts[i].append(pos)
                pos += size
    out = _empty(props, count, bo)
    for i, p in enumerate(props):
        at = np.frombuffer(starts[i], dtype=np.int64)
        item = np.dtype(p.dtype).itemsize
        # every byte offset of the buffer read as one value of this type: gathering from it
        # costs 8 bytes an index (not 8 per byte of every value)
        at_byte = np.ndarray(shape=(total - item + 1,), dtype=bo + p.dtype, buffer=buf,
                             strides=(1,))
        if p.is_list:
            n = np.frombuffer(lengths[i], dtype=np.int64)
            ends = np.cumsum(n)
            item_at = np.repeat(at - (ends - n) * item, n)
            step = np.arange(int(ends[-1]), dtype=np.int64)
            step *= item
            item_at += step
            del step
            values = at_byte[item_at]
            del item_at
            out[p.name] = _ragged_lists(values, n)
        else:
            out[p.name] = at_byte[at]
    return out, pos


class _AsciiElement:
    """The body rows of one ascii element and how to name a value in an error message.

    rows: the element's non-blank body lines; line_of(i): the file line number of rows[i];
    starts: (R,) index of each row's first token in the element's flat token array.
    """

    def __init__(self, path: Path, name: str, rows: list[bytes],
                 line_of: Callable[[int], int]) -> None:
        self.path, self.name, self.rows, self.line_of = path, name, rows, line_of
        self.starts = np.zeros(len(rows), dtype=np.int64)

    def error(self, row: int, message: str) -> FormatError:
        return FormatError(f"{self.path}: malformed ascii body, line {self.line_of(row)} of "
                           f"element '{self.name}': {message}")

    def convert(self, values: np.ndarray, code: str, what: str, at: np.ndarray) -> np.ndarray:
        """Parsed tokens (float64, any shape) -> ``code``, rejecting values the type cannot
        hold (300 in a uchar, -1 in a uint, 1.9 in an int, 1e39 in a float) with the line.

        at: flat token index of each value (same shape), to name the offending token.
        """
        with np.errstate(over="ignore", invalid="ignore"):
            if code[0] == "f":
                out = values.astype(code)
                bad = np.isfinite(values) & ~np.isfinite(out)
                expected = f"within {TYPE_NAMES[code]} range"
            else:
                info = np.iinfo(code)
                bad = ~((values >= info.min) & (values <= info.max)
                        & (np.floor(values) == values))
                expected = f"an integer in {info.min}..{info.max}"
                out = None
        if bad.any():
            token_index = int(at.ravel()[np.flatnonzero(bad.ravel())[0]])
            row = int(np.searchsorted(self.starts, token_index, side="right")) - 1
            tokens = self.rows[row].split()
            token = tokens[token_index - self.starts[row]].decode(errors="replace")
            raise self.error(row, f"{what} ({TYPE_NAMES[code]}) value {token!r} is not "
                             f"{expected}")
        return values.astype(code) if out is None else out


def _parse_ascii_rows(el: _AsciiElement, props: list[PlyProperty]) -> np.ndarray:
    """All rows of an element at once: every token parsed to float64 in one go, then each
    property gathered for all rows (lists of varying length included), checked against its
    type. Work and memory are linear in the element's text."""
    rows = el.rows
    count = len(rows)
    out = _empty(props, count, "=")
    if count == 0:
        return out
    lengths = np.fromiter((len(r.split()) for r in rows), dtype=np.int64, count=count)
    try:
        flat = np.array(b" ".join(rows).split(), dtype=np.float64)
    except ValueError:
        for i, row in enumerate(rows):
            try:
                np.array(row.split(), dtype=np.float64)
            except ValueError as exc:
                raise el.error(i, "not a number in "
                               f"{row.decode(errors='replace').strip()[:60]!r}") from exc
        raise
    el.starts = np.cumsum(lengths) - lengths
    pos = np.zeros(count, dtype=np.int64)  # next token of each row

    def first(mask: np.ndarray) -> int:
        return int(np.flatnonzero(mask)[0])

    for p in props:
        if (pos >= lengths).any():
            i = first(pos >= lengths)
            raise el.error(i, f"expected {len(props)} properties, got "
                           f"{rows[i].decode(errors='replace').strip()[:60]!r}")
        at = el.starts + pos
        if not p.is_list:
            out[p.name] = el.convert(flat[at], p.dtype, repr(p.name), at)
            pos += 1
            continue
        n = el.convert(flat[at], p.len_dtype, f"list length of '{p.name}'", at)\
            .astype(np.int64)
        short = (n < 0) | (pos + 1 + n > lengths)
        if short.any():
            i = first(short)
            raise el.error(i, f"list '{p.name}' declares {n[i]} values, "
                           f"{lengths[i] - pos[i] - 1} present")
        if (n == n[0]).all():
            index = (at + 1)[:, None] + np.arange(n[0])
            out[p.name] = _fixed_lists(el.convert(flat[index], p.dtype, repr(p.name), index))
        else:
            ends = np.cumsum(n)
            index = np.repeat(at + 1 - (ends - n), n) + np.arange(int(ends[-1]))
            values = el.convert(flat[index], p.dtype, repr(p.name), index)
            out[p.name] = _ragged_lists(values, n)
        pos += 1 + n
    if (pos != lengths).any():
        i = first(pos != lengths)
        raise el.error(i, f"{lengths[i] - pos[i]} values too many")
    return out


def _ascii_rows(rows: list[bytes], data: np.ndarray) -> AsciiRows:
    rows = [r.strip() for r in rows]
    starts = np.zeros(len(rows) + 1, dtype=np.int64)
    np.cumsum(np.fromiter((len(r) for r in rows), dtype=np.int64, count=len(rows)),
              out=starts[1:])
    return AsciiRows(b"".join(rows), starts, data)


def shortest_text(values: np.ndarray, dtype: str) -> list[str]:
    """The shortest text that reads back to each value of type ``dtype`` ('f4', 'i2', ...)."""
    if dtype[0] != "f":
        return [str(int(v)) for v in values]
    kind = np.float32 if dtype == "f4" else np.float64
    out = []
    for v in np.asarray(values, dtype=kind):
        if not np.isfinite(v):
            out.append("nan" if np.isnan(v) else ("inf" if v > 0 else "-inf"))
        elif v == 0 or 1e-5 <= abs(v) < 1e16:
            out.append(np.format_float_positional(v, unique=True, trim="-"))
        else:
            out.append(np.format_float_scientific(v, unique=True, trim="-"))
    return out


def _read_file(path: Path) -> bytearray:
    """The whole file, in a writable buffer (a binary body's elements are views of it, not
    copies); refuses anything but a regular file before reading (a FIFO or a device would
    block or never end)."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    with os.fdopen(fd, "rb") as stream:
        status = os.fstat(stream.fileno())
        check_regular(path, status.st_mode)
        raw = bytearray(status.st_size)
        del raw[stream.readinto(raw) or 0:]
        raw += stream.read()  # grown since the stat: to its end, as a plain read would
        return raw


def read_ply(path: str | Path) -> PlySource:
    """Read a PLY file verbatim. Raises FormatError naming the file on any problem.

    Work and memory are bounded by the file size: the header's element counts are checked
    against the body size before anything is allocated.
    """
    path = Path(path)
    raw = _read_file(path)
    if not raw:
        raise FormatError(f"{path}: empty file")
    header = parse_header(path, raw)
    _check_declared_size(path, header, len(raw) - header.size)
    elements: list[PlyElementData] = []
    if header.text:
        raw = bytes(raw)  # lines as bytes (the buffer is released here)
        underscore = raw.find(b"_", header.size)
        if underscore >= 0:  # Python would read 1_000 as 1000; PLY has no digit separators
            line = header.lines + 1 + raw.count(b"\n", header.size, underscore)
            raise FormatError(f"{path}: malformed ascii body, line {line}: '_' in a number "
                              "(not PLY syntax)")
        lines = [ln for ln in raw[header.size:].splitlines() if ln.strip()]

        def line_of(index: int) -> int:  # file line number of the index-th non-blank body line
            seen = -1
            for number, ln in enumerate(raw[header.size:].splitlines(), header.lines + 1):
                seen += bool(ln.strip())
                if seen == index:
                    return number
            return -1

        pos = 0
        for name, count, props in header.elements:
            rows = lines[pos: pos + count]
            if len(rows) < count:
                raise FormatError(f"{path}: truncated ascii body: element '{name}' declares "
                                  f"{count} rows, {len(rows)} present")
            parts = []
            for first in range(0, max(count, 1), ASCII_CHUNK_ROWS):  # bounded token lists
                start = pos + first
                el = _AsciiElement(path, name, rows[first:first + ASCII_CHUNK_ROWS],
                                   lambda i, s=start: line_of(s + i))
                parts.append(_parse_ascii_rows(el, props))
            data = parts[0] if len(parts) == 1 else np.concatenate(parts)
            elements.append(PlyElementData(name, props, data, _ascii_rows(rows, data)))
            pos += count
        if pos < len(lines):
            raise FormatError(f"{path}: {len(lines) - pos} ascii lines after the last element "
                              f"(from line {line_of(pos)}); the header's element counts do not "
                              "match the body")
    else:
        buf = memoryview(raw)
        offset = header.size
        for name, count, props in header.elements:
            data, offset = _read_binary_element(path, buf, offset, name, count, props,
                                                header.byte_order)
            elements.append(PlyElementData(name, props, data))
        if raw[offset:].strip():
            raise FormatError(f"{path}: {len(raw) - offset} bytes after the last element; "
                              "the header's element counts do not match the body")
    return PlySource(elements, header.comments, header.obj_info, header.text,
                     header.byte_order)


def header_text(source: PlySource, text: bool, byte_order: str) -> bytes:
    """The header bytes of ``source`` (its elements, counts and properties) in the given
    encoding (``byte_order`` "<" or ">" when binary)."""
    fmt = "ascii" if text else ("binary_big_endian" if byte_order == ">"
                                else "binary_little_endian")
    lines = ["ply", f"format {fmt} 1.0"]
    lines += [f"comment {c}" for c in source.comments]
    lines += [f"obj_info {c}" for c in source.obj_info]
    for el in source.elements:
        lines.append(f"element {el.name} {el.count}")
        for p in el.properties:
            if p.is_list:
                lines.append(f"property list {p.len_type_name} {p.type_name} {p.name}")
            else:
                lines.append(f"property {p.type_name} {p.name}")
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def _list_lengths(column: np.ndarray) -> np.ndarray:
    return np.fromiter((len(v) for v in column), dtype=np.int64, count=len(column))


def _write_binary_element(out: io.BufferedIOBase, el: PlyElementData, bo: str) -> None:
    props = el.properties
    if not any(p.is_list for p in props):
        dtype = np.dtype([(p.name, bo + p.dtype) for p in props])
        # the rows' own buffer when already in that layout (no whole-element byte copy)
        out.write(np.ascontiguousarray(el.data.astype(dtype, copy=False)).view(np.uint8))
        return
    if el.count == 0:
        return
    lengths = {p.name: _list_lengths(el.data[p.name]) for p in props if p.is_list}
    if all((v == v[0]).all() for v in lengths.values()):
        packed = np.empty(el.count, dtype=_packed_dtype(
            props, {n: int(v[0]) for n, v in lengths.items()}, bo))
        for p in props:
            if p.is_list:
                packed[p.name + "\nlen"] = lengths[p.name]
                packed[p.name] = np.stack(el.data[p.name]).reshape(el.count, -1) \
                    if lengths[p.name][0] > 0 else np.empty((el.count, 0))
            else:
                packed[p.name] = el.data[p.name]
        out.write(packed.tobytes())
        return
    for row in el.data:
        for p in props:
            if p.is_list:
                values = np.asarray(row[p.name])
                out.write(np.asarray(len(values), dtype=bo + p.len_dtype).tobytes())
                out.write(values.astype(bo + p.dtype).tobytes())
            else:
                out.write(np.asarray(row[p.name], dtype=bo + p.dtype).tobytes())


def _format_ascii_column(values: np.ndarray, dtype: str) -> np.ndarray:
    if dtype[0] == "f":
        # %.9g round-trips float32 exactly, %.17g float64.
        fmt = "%.9g" if dtype == "f4" else "%.17g"
        return np.char.mod(fmt, values.astype(np.float64))
    return np.char.mod("%d", values.astype(np.int64))


def _kept_rows(el: PlyElementData) -> list[bytes] | None:
    """The element's rows as text, reusing the text read for every unchanged value (the
    shortest round-trip text for changed ones); None when the element has no text to reuse
    (not read from ascii, other properties or rows, or changed list properties)."""
    text = el.ascii_text
    if text is None or len(text.starts) - 1 != el.count:
        return None
    orig = text.original
    names = [p.name for p in el.properties]
    if list(orig.dtype.names or ()) != names or orig.dtype != el.data.dtype:
        return None
    body, starts = text.body, text.starts
    if el.data is orig:
        return [body[starts[i]:starts[i + 1]] for i in range(el.count)]
    if any(p.is_list for p in el.properties):
        return None
    changed = np.zeros((el.count, len(names)), dtype=bool)
    for j, p in enumerate(el.properties):
        a, b = el.data[p.name], orig[p.name]
        diff = a != b
        if p.dtype[0] == "f":
            diff &= ~(np.isnan(a) & np.isnan(b))
        changed[:, j] = diff
    rows = [body[starts[i]:starts[i + 1]] for i in range(el.count)]
    for i in np.flatnonzero(changed.any(axis=1)):
        tokens = rows[i].split()
        for j in np.flatnonzero(changed[i]):
            p = el.properties[j]
            tokens[j] = shortest_text(el.data[p.name][i:i + 1], p.dtype)[0].encode()
        rows[i] = b" ".join(tokens)
    return rows


def _write_ascii_element(out: io.BufferedIOBase, el: PlyElementData) -> None:
    if el.count == 0:
        return
    kept = _kept_rows(el)
    if kept is not None:
        for first in range(0, len(kept), ASCII_CHUNK_ROWS):
            out.write(b"\n".join(kept[first:first + ASCII_CHUNK_ROWS]) + b"\n")
        return
    columns: list[np.ndarray] = []  # one string per row and property
    for p in el.properties:
        if p.is_list:
            lists = el.data[p.name]
            lengths = _list_lengths(lists)
            if (lengths == lengths[0]).all() and lengths[0] > 0:
                values = _format_ascii_column(np.stack(lists).reshape(el.count, -1), p.dtype)
                text = [f"{n} " + " ".join(row)
                        for n, row in zip(lengths, values.tolist(), strict=True)]
            else:
                text = [" ".join([str(len(v))] + _format_ascii_column(np.asarray(v), p.dtype)
                                 .tolist()) for v in lists]
            columns.append(np.asarray(text, dtype=object))
        else:
            columns.append(_format_ascii_column(el.data[p.name], p.dtype).astype(object))
    rows = [" ".join(parts) for parts in zip(*columns, strict=True)]
    out.write(("\n".join(rows) + "\n").encode("ascii"))


def write_ply(source: PlySource, out: io.BufferedIOBase, *, text: bool | None = None,
              byte_order: str | None = None) -> None:
    """Write ``source`` to the open binary stream ``out`` (format defaults to the source's)."""
    text = source.text if text is None else text
    bo = source.byte_order if byte_order is None else byte_order
    out.write(header_text(source, text, bo))
    for el in source.elements:
        if text:
            _write_ascii_element(out, el)
        else:
            _write_binary_element(out, el, bo)
