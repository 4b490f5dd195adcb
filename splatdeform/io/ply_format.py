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
from dataclasses import dataclass
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
SPAN_BLOCK = 1 << 24  # ascii body bytes scanned for row boundaries at a time
_SPACE = np.zeros(256, dtype=bool)
_SPACE[list(b" \t\n\r\x0b\x0c")] = True  # bytes.strip()'s whitespace
_INFINITY = (b"inf", b"infinity")  # the literal spellings of an infinity (any case, any sign)


@dataclass
class AsciiText(AsciiRows):
    """An ascii element's rows as read plus the exact bytes around them, so that a save of an
    unchanged element (and header) reproduces the file byte for byte: line ends (CRLF, LF, CR),
    blank lines, leading and trailing spaces, a final newline or its absence.

    raw: the whole file as read (shared by every element of the file); header: its header
    bytes up to and including the ``end_header`` line; header_normal: :func:`header_text` of
    the source as read (a save writes ``header`` verbatim when its header text is still this);
    newline: the file's line end (that of its first line), used for every line a save writes
    anew; spans: (R, 2) int64 offsets in ``raw`` of each row's text; begin / end: the bytes of
    ``raw`` this element owns (from the line after the previous element's last row to the line
    end after its own last row; the last element also owns whatever follows).
    """

    raw: bytes = b""
    header: bytes = b""
    header_normal: bytes = b""
    newline: bytes = b"\n"
    spans: np.ndarray | None = None
    begin: int = 0
    end: int = 0


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


def check_declared_size(path: Path, header: PlyHeader, body_bytes: int) -> None:
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
    # sits (bounded: count * the smallest row fits the file, checked by check_declared_size),
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
        # (T,) bool over the flat tokens: a number too large for float64 (1e400), which
        # parses as an infinity but is not one of the literal spellings (inf, Infinity)
        self.overflow: np.ndarray | None = None

    def error(self, row: int, message: str) -> FormatError:
        return FormatError(f"{self.path}: malformed ascii body, line {self.line_of(row)} of "
                           f"element '{self.name}': {message}")

    def convert(self, values: np.ndarray, code: str, what: str, at: np.ndarray) -> np.ndarray:
        """Parsed tokens (float64, any shape) -> ``code``, rejecting values the type cannot
        hold (300 in a uchar, -1 in a uint, 1.9 in an int, 1e39 in a float, 1e400 in any type)
        with the line; the literal tokens inf / nan are kept in float types.

        at: flat token index of each value (same shape), to name the offending token.
        """
        with np.errstate(over="ignore", invalid="ignore"):
            if code[0] == "f":
                out = values.astype(code)
                bad = np.isfinite(values) & ~np.isfinite(out)
                if self.overflow is not None:
                    bad |= self.overflow[at]
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
    tokens = b" ".join(rows).split()
    try:
        flat = np.array(tokens, dtype=np.float64)
    except ValueError:
        for i, row in enumerate(rows):
            try:
                np.array(row.split(), dtype=np.float64)
            except ValueError as exc:
                raise el.error(i, "not a number in "
                               f"{row.decode(errors='replace').strip()[:60]!r}") from exc
        raise
    infinite = np.flatnonzero(np.isinf(flat))
    if infinite.size:  # 1e400 overflows to inf in the parse: refused like 1e39 in a float
        el.overflow = np.zeros(flat.size, dtype=bool)
        el.overflow[infinite] = [tokens[i].lstrip(b"+-").lower() not in _INFINITY
                                 for i in infinite]
    del tokens
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


def _row_spans(raw: bytes, start: int) -> np.ndarray:
    """(R, 2) int64 [begin, end) in ``raw`` of every non-blank line's text from ``start`` on
    (split at \\r, \\n or \\r\\n as bytes.splitlines does, without leading and trailing
    whitespace as bytes.strip). Vectorised over blocks of :data:`SPAN_BLOCK` bytes; only lines
    with more than a few spaces at an end are trimmed one by one."""
    data = np.frombuffer(raw, dtype=np.uint8)
    parts = [np.empty((0, 2), dtype=np.int64)]
    pos, n = start, len(raw)
    while pos < n:
        stop = min(n, pos + SPAN_BLOCK)
        if stop < n:  # end the block at a line break
            cut = max(raw.rfind(b"\n", pos, stop), raw.rfind(b"\r", pos, stop))
            stop = cut + 1 if cut >= pos else _line_end(raw, stop)
        seg = data[pos:stop]
        breaks = np.flatnonzero((seg == 10) | (seg == 13))  # \r\n: an empty line between
        begin = np.concatenate([[0], breaks + 1])
        end = np.concatenate([breaks, [seg.size]])
        space = _SPACE[seg]
        for _ in range(4):
            grow = np.flatnonzero(begin < end)
            grow = grow[space[begin[grow]]]
            if not grow.size:
                break
            begin[grow] += 1
        for _ in range(4):
            shrink = np.flatnonzero(begin < end)
            shrink = shrink[space[end[shrink] - 1]]
            if not shrink.size:
                break
            end[shrink] -= 1
        rest = np.flatnonzero(begin < end)
        rest = rest[space[begin[rest]] | space[end[rest] - 1]]
        for i in rest.tolist():  # long runs of spaces at a line's end: trimmed by bytes.strip
            line = raw[pos + begin[i]:pos + end[i]]
            begin[i] += len(line) - len(line.lstrip())
            end[i] = begin[i] + len(line.strip())
        keep = begin < end
        parts.append(np.stack([begin[keep], end[keep]], axis=1) + pos)
        pos = stop
    return np.concatenate(parts)


def _line_breaks(raw: bytes, start: int, stop: int) -> int:
    """Line breaks (\\n, \\r or \\r\\n, each one) in raw[start:stop]."""
    return (raw.count(b"\n", start, stop) + raw.count(b"\r", start, stop)
            - raw.count(b"\r\n", start, stop))


def _line_end(raw: bytes, pos: int) -> int:
    """The offset just past the line break at or after ``pos`` (the end of ``raw`` if none)."""
    cr, lf = raw.find(b"\r", pos), raw.find(b"\n", pos)
    if lf >= 0 and (cr < 0 or lf < cr):
        return lf + 1
    if cr >= 0:
        return cr + 2 if raw[cr + 1:cr + 2] == b"\n" else cr + 1
    return len(raw)


def _newline(header: bytes) -> bytes:
    """A file's line end: that of its first line (``ply``)."""
    first = header.find(b"\n")
    return b"\r\n" if first > 0 and header[first - 1:first] == b"\r" else b"\n"


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
    check_declared_size(path, header, len(raw) - header.size)
    elements: list[PlyElementData] = []
    if header.text:
        raw = bytes(raw)  # lines as bytes (the buffer is released here)
        underscore = raw.find(b"_", header.size)
        if underscore >= 0:  # Python would read 1_000 as 1000; PLY has no digit separators
            line = header.lines + 1 + raw.count(b"\n", header.size, underscore)
            raise FormatError(f"{path}: malformed ascii body, line {line}: '_' in a number "
                              "(not PLY syntax)")
        lines = [ln for ln in raw[header.size:].splitlines() if ln.strip()]
        spans = _row_spans(raw, header.size)  # where each of them is in the file
        exact = spans.shape[0] == len(lines)  # always (else: saves write normalised text)

        def line_of(index: int) -> int:  # file line number of the index-th non-blank body line
            return header.lines + 1 + _line_breaks(raw, header.size, int(spans[index, 0]))

        newline = _newline(raw[:header.size])
        pos, begin = 0, header.size
        for number, (name, count, props) in enumerate(header.elements):
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
            last = number == len(header.elements) - 1
            end = len(raw) if last or not exact else (
                _line_end(raw, int(spans[pos + count - 1, 1])) if count else begin)
            text = _ascii_rows(rows, data)
            elements.append(PlyElementData(name, props, data, AsciiText(
                text.body, text.starts, data, raw=raw, header=raw[:header.size],
                newline=newline, spans=spans[pos: pos + count] if exact else None,
                begin=begin, end=end)))
            pos, begin = pos + count, end
        if pos < len(lines):
            raise FormatError(f"{path}: {len(lines) - pos} ascii lines after the last element "
                              f"(from line {line_of(pos)}); the header's element counts do not "
                              "match the body")
        normal = header_text(PlySource(elements, header.comments, header.obj_info, True,
                                       header.byte_order), True, header.byte_order)
        for element in elements:
            element.ascii_text.header_normal = normal
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


def header_text(source: PlySource, text: bool, byte_order: str, newline: bytes = b"\n"
                ) -> bytes:
    """The header bytes of ``source`` (its elements, counts and properties) in the given
    encoding (``byte_order`` "<" or ">" when binary), each line ended by ``newline``."""
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
    return newline.join(line.encode("ascii") for line in lines) + newline


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


def _changed_rows(el: PlyElementData) -> dict[int, bytes] | None:
    """The new text of every row whose values changed (row index -> its values, the text read
    for every unchanged value and the shortest round-trip text for changed ones); {} when no
    value changed; None when the element has no text to reuse (not read from ascii, other
    properties or rows, or changed list properties)."""
    text = el.ascii_text
    if text is None or len(text.starts) - 1 != el.count:
        return None
    orig = text.original
    names = [p.name for p in el.properties]
    if list(orig.dtype.names or ()) != names or orig.dtype != el.data.dtype:
        return None
    if el.data is orig:
        return {}
    if any(p.is_list for p in el.properties):
        return None
    changed = np.zeros((el.count, len(names)), dtype=bool)
    for j, p in enumerate(el.properties):
        a, b = el.data[p.name], orig[p.name]
        diff = a != b
        if p.dtype[0] == "f":
            diff &= ~(np.isnan(a) & np.isnan(b))
        changed[:, j] = diff
    body, starts = text.body, text.starts
    rows: dict[int, bytes] = {}
    for i in np.flatnonzero(changed.any(axis=1)).tolist():
        tokens = body[starts[i]:starts[i + 1]].split()
        for j in np.flatnonzero(changed[i]):
            p = el.properties[j]
            tokens[j] = shortest_text(el.data[p.name][i:i + 1], p.dtype)[0].encode()
        rows[i] = b" ".join(tokens)
    return rows


def _write_kept(out: io.BufferedIOBase, text: AsciiText, rows: dict[int, bytes]) -> None:
    """The element's bytes as read, with the text of each changed row replaced (its line's
    leading and trailing spaces and line end kept)."""
    raw, spans = memoryview(text.raw), text.spans
    pos = text.begin
    for i in sorted(rows):
        start, stop = (int(v) for v in spans[i])
        out.write(raw[pos:start])
        out.write(rows[i])
        pos = stop
    out.write(raw[pos:text.end])


def _kept_rows(el: PlyElementData) -> list[bytes] | None:
    """Every row's text (see :func:`_changed_rows`), without the bytes around them."""
    rows = _changed_rows(el)
    if rows is None:
        return None
    body, starts = el.ascii_text.body, el.ascii_text.starts
    return [rows.get(i) or body[starts[i]:starts[i + 1]] for i in range(el.count)]


def _write_ascii_element(out: io.BufferedIOBase, el: PlyElementData,
                         newline: bytes = b"\n") -> None:
    text = el.ascii_text
    rows = _changed_rows(el)
    if rows is not None and isinstance(text, AsciiText) and text.spans is not None:
        _write_kept(out, text, rows)  # an empty element: the blank lines it owns, if any
        return
    if el.count == 0:
        return
    kept = _kept_rows(el)
    if kept is not None:
        for first in range(0, len(kept), ASCII_CHUNK_ROWS):
            out.write(newline.join(kept[first:first + ASCII_CHUNK_ROWS]) + newline)
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
    out.write(newline.join(row.encode("ascii") for row in rows) + newline)


def write_ply(source: PlySource, out: io.BufferedIOBase, *, text: bool | None = None,
              byte_order: str | None = None) -> None:
    """Write ``source`` to the open binary stream ``out`` (format defaults to the source's)."""
    text = source.text if text is None else text
    bo = source.byte_order if byte_order is None else byte_order
    read = next((el.ascii_text for el in source.elements
                 if isinstance(el.ascii_text, AsciiText)), None)
    newline = read.newline if text and read is not None else b"\n"
    header = header_text(source, text, bo, newline)
    if read is not None and text and header_text(source, text, bo) == read.header_normal:
        header = read.header  # the header as read: what it says has not changed
    out.write(header)
    for el in source.elements:
        if text:
            _write_ascii_element(out, el, newline)
        else:
            _write_binary_element(out, el, bo)
