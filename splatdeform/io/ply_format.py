"""Raw PLY reading and writing: header, ascii and binary (little/big endian) bodies.

Why not plyfile's own reader/writer: it parses ascii rows and binary list rows in a Python loop
per row (seconds for a 100k-face mesh) and its errors do not name the file. This module parses the
header itself (errors name the file and line), reads bodies with numpy in bulk, and falls back to
a per-row loop only for variable-length lists. The result is a :class:`PlySource` that a save
writes back unchanged: same elements, property names, type spellings, order and comments.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..model import PlyElementData, PlyProperty, PlySource

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


class _Header:
    def __init__(self) -> None:
        self.text = False
        self.byte_order = "<"
        self.comments: list[str] = []
        self.obj_info: list[str] = []
        self.elements: list[tuple[str, int, list[PlyProperty]]] = []
        self.size = 0


def _parse_header(path: Path, raw: bytes) -> _Header:
    if not raw.startswith(b"ply"):
        raise FormatError(f"{path}: not a PLY file (it does not start with 'ply')")
    end = raw.find(b"end_header", 0, MAX_HEADER_BYTES)
    if end < 0:
        raise FormatError(f"{path}: malformed PLY header: no 'end_header' line")
    newline = raw.find(b"\n", end)
    header = _Header()
    header.size = len(raw) if newline < 0 else newline + 1
    try:
        lines = raw[:end].decode("ascii").splitlines()
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: malformed PLY header: non-ASCII bytes") from exc
    seen_format = False
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words:
            continue
        where = f"{path}: malformed PLY header, line {number} ({line.strip()!r})"
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
            if len(words) != 3 or not words[2].isdigit():
                raise FormatError(f"{where}: expected 'element <name> <count>'")
            header.elements.append((words[1], int(words[2]), []))
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
                props.append(PlyProperty(words[4], TYPE_CODES[words[3]], words[3], True,
                                         TYPE_CODES[words[2]], words[2]))
            elif len(words) == 3 and words[1] in TYPE_CODES:
                props.append(PlyProperty(words[2], TYPE_CODES[words[1]], words[1]))
            else:
                raise FormatError(f"{where}: expected 'property <type> <name>' or "
                                  "'property list <count type> <type> <name>'")
            if [p.name for p in props].count(props[-1].name) > 1:
                raise FormatError(f"{where}: duplicate property {props[-1].name!r}")
        else:
            raise FormatError(f"{where}: unknown keyword {key!r}")
    if not seen_format:
        raise FormatError(f"{path}: malformed PLY header: no 'format' line")
    return header


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


def _split_lists(packed: np.ndarray, props: list[PlyProperty], byte_order: str) -> np.ndarray:
    """Packed fixed-length records -> the object-field layout."""
    out = _empty(props, packed.shape[0], byte_order)
    for p in props:
        if p.is_list:
            values = np.ascontiguousarray(packed[p.name])
            column = np.empty(packed.shape[0], dtype=object)
            column[:] = list(values)
            out[p.name] = column
        else:
            out[p.name] = packed[p.name]
    return out


def _read_binary_element(path: Path, buf: memoryview, offset: int, name: str, count: int,
                         props: list[PlyProperty], bo: str) -> tuple[np.ndarray, int]:
    total = len(buf)

    def truncated(needed: int) -> FormatError:
        return FormatError(f"{path}: truncated binary body: element '{name}' needs at least "
                           f"{needed} more bytes, {max(total - offset, 0)} left "
                           "(file cut short, or the header's count is wrong)")

    if not any(p.is_list for p in props):
        dtype = np.dtype([(p.name, bo + p.dtype) for p in props])
        if offset + dtype.itemsize * count > total:
            raise truncated(dtype.itemsize * count)
        data = np.frombuffer(buf, dtype=dtype, count=count, offset=offset).copy()
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
            lengths[p.name] = n
            pos += size + n * np.dtype(p.dtype).itemsize
        else:
            pos += np.dtype(p.dtype).itemsize
    packed_dtype = _packed_dtype(props, lengths, bo)
    if offset + packed_dtype.itemsize * count <= total:
        packed = np.frombuffer(buf, dtype=packed_dtype, count=count, offset=offset)
        if all((packed[n + "\nlen"] == L).all() for n, L in lengths.items()):
            return _split_lists(packed, props, bo), offset + packed_dtype.itemsize * count
    # Variable-length lists: one row at a time.
    out = _empty(props, count, bo)
    pos = offset
    for row in range(count):
        for p in props:
            if p.is_list:
                size = np.dtype(p.len_dtype).itemsize
                if pos + size > total:
                    raise truncated(size)
                n = int(np.frombuffer(buf, dtype=bo + p.len_dtype, count=1, offset=pos)[0])
                pos += size
                nbytes = n * np.dtype(p.dtype).itemsize
                if pos + nbytes > total:
                    raise truncated(nbytes)
                out[p.name][row] = np.frombuffer(buf, dtype=bo + p.dtype, count=n,
                                                 offset=pos).copy()
                pos += nbytes
            else:
                size = np.dtype(p.dtype).itemsize
                if pos + size > total:
                    raise truncated(size)
                out[p.name][row] = np.frombuffer(buf, dtype=bo + p.dtype, count=1, offset=pos)[0]
                pos += size
    return out, pos


def _parse_ascii_rows(path: Path, rows: list[bytes], first_line: int, name: str,
                      props: list[PlyProperty]) -> np.ndarray:
    count = len(rows)
    out = _empty(props, count, "=")
    if count == 0:
        return out
    widths = {len(r.split()) for r in rows}
    try:
        if len(widths) == 1:
            width = widths.pop()
            table = np.array(b" ".join(rows).split(), dtype=np.float64).reshape(count, width)
            col = 0
            for p in props:
                if p.is_list:
                    n = int(table[0, col])
                    if not (table[:, col] == n).all() or col + 1 + n > width:
                        raise ValueError("ragged")
                    values = table[:, col + 1: col + 1 + n].astype(p.dtype)
                    column = np.empty(count, dtype=object)
                    column[:] = list(values)
                    out[p.name] = column
                    col += 1 + n
                else:
                    out[p.name] = table[:, col].astype(p.dtype)
                    col += 1
            if col != width:
                raise ValueError("width")
            return out
    except ValueError:
        pass
    for i, row in enumerate(rows):
        tokens = row.split()
        pos = 0
        try:
            for p in props:
                if p.is_list:
                    n = int(tokens[pos])
                    out[p.name][i] = np.array(tokens[pos + 1: pos + 1 + n], dtype=np.float64)\
                        .astype(p.dtype)
                    if len(out[p.name][i]) != n:
                        raise IndexError
                    pos += 1 + n
                else:
                    out[p.name][i] = np.float64(tokens[pos]).astype(p.dtype) \
                        if p.dtype[0] == "f" else int(tokens[pos])
                    pos += 1
        except (IndexError, ValueError) as exc:
            raise FormatError(f"{path}: malformed ascii body, line {first_line + i} of element "
                              f"'{name}': expected {len(props)} properties, got "
                              f"{row.decode(errors='replace').strip()[:60]!r}") from exc
        if pos != len(tokens):
            raise FormatError(f"{path}: malformed ascii body, line {first_line + i} of element "
                              f"'{name}': {len(tokens) - pos} values too many")
    return out


def read_ply(path: str | Path) -> PlySource:
    """Read a PLY file verbatim. Raises FormatError naming the file on any problem."""
    path = Path(path)
    raw = path.read_bytes()
    if not raw:
        raise FormatError(f"{path}: empty file")
    header = _parse_header(path, raw)
    elements: list[PlyElementData] = []
    if header.text:
        lines = [ln for ln in raw[header.size:].splitlines() if ln.strip()]
        header_lines = raw[: header.size].count(b"\n")
        pos = 0
        for name, count, props in header.elements:
            rows = lines[pos: pos + count]
            if len(rows) < count:
                raise FormatError(f"{path}: truncated ascii body: element '{name}' declares "
                                  f"{count} rows, {len(rows)} present")
            elements.append(PlyElementData(name, props, _parse_ascii_rows(
                path, rows, header_lines + pos + 1, name, props)))
            pos += count
        if pos < len(lines):
            raise FormatError(f"{path}: {len(lines) - pos} ascii lines after the last element; "
                              "the header's element counts do not match the body")
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


def _header_text(source: PlySource, text: bool, byte_order: str) -> bytes:
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
        out.write(el.data.astype(dtype, copy=False).tobytes())
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


def _write_ascii_element(out: io.BufferedIOBase, el: PlyElementData) -> None:
    if el.count == 0:
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
    out.write(_header_text(source, text, bo))
    for el in source.elements:
        if text:
            _write_ascii_element(out, el)
        else:
            _write_binary_element(out, el, bo)
