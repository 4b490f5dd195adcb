"""glTF 2.0 with ``KHR_gaussian_splatting``: ``.glb`` (binary container) and ``.gltf`` (JSON with
the buffer as a base64 data URI, or a file beside it on read).

A splat primitive (mode 0, POINTS, with the ``KHR_gaussian_splatting`` extension: ``kernel``
``ellipse``, ``colorSpace``) holds POSITION, ``KHR_gaussian_splatting:ROTATION`` (VEC4 x y z w),
``:SCALE`` (VEC3, linear standard deviations, as the pinned splat-transform writes),
``:OPACITY`` (SCALAR, after the sigmoid, 0..1), ``:SH_DEGREE_0_COEF_0`` (VEC3 f_dc) and
``:SH_DEGREE_l_COEF_n`` (VEC3 r g b of each higher coefficient), plus an optional COLOR_0
fallback. Written as float32 (the linear scale and post-sigmoid opacity are the only conversions,
within an ulp of float32 arithmetic); read also accepts the normalised integer types the
extension allows.

Axes: glTF is +y up (x left, z front seen from the asset's front); PLY space is y down. The two
differ by 180 degrees about z: x and y flip, each quaternion is pre-multiplied by that turn,
and the SH coefficients odd in x + y change sign.
"""

from __future__ import annotations

import base64
import json
import re
import struct
import zlib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from ..errors import FormatError, InputError
from ..model import PointModel
from . import spz
from .checks import check_fits
from .regular import member_path, open_regular, read_regular
from .splat_model import to_model
from .splats import (
    SH_COEFFS,
    SplatFields,
    dc_to_color,
    fields_of,
    normalised_quaternions,
    note_lossy,
    sigmoid,
)

EXT = "KHR_gaussian_splatting"
#: SPZ compression, nested in the primitive's KHR_gaussian_splatting extension (the draft and
#: its v2 name); the SPZ blob's versions are the ones :mod:`.spz` reads
SPZ_EXTS = ("KHR_gaussian_splatting_compression_spz", "KHR_gaussian_splatting_compression_spz_2")
GLB_MAGIC = 0x46546C67  # 'glTF'
JSON_CHUNK, BIN_CHUNK = 0x4E4F534A, 0x004E4942
FLOAT, UBYTE, BYTE, USHORT, SHORT = 5126, 5121, 5120, 5123, 5122
COMPONENT = {FLOAT: "<f4", UBYTE: "u1", BYTE: "i1", USHORT: "<u2", SHORT: "<i2"}
NORMALISE = {UBYTE: lambda v: v / 255.0, USHORT: lambda v: v / 65535.0,
             BYTE: lambda v: np.maximum(v / 127.0, -1.0),
             SHORT: lambda v: np.maximum(v / 32767.0, -1.0)}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
# SH rest sign under the 180-degree turn about z (x -> -x, y -> -y), coefficients in PLY order
SH_FLIP, FLIP = spz.LUF_SH_FLIP, spz.LUF_FLIP
OPACITY_EPS = 1e-7


def _sh_names(degree: int) -> list[str]:
    return [f"{EXT}:SH_DEGREE_{ell}_COEF_{n}" for ell in range(1, degree + 1)
            for n in range(2 * ell + 1)]


def _turn(q_wxyz: np.ndarray) -> np.ndarray:
    """(N, 4) w x y z -> the 180-degree turn about z applied first: (0,0,0,1) * q."""
    w, x, y, z = q_wxyz.T
    return np.stack([-z, -y, x, w], axis=1)


def _unturn(q_wxyz: np.ndarray) -> np.ndarray:
    w, x, y, z = q_wxyz.T
    return np.stack([z, y, -x, -w], axis=1)


# --------------------------------------------------------------------------------------------
# reading
#
# Every value the JSON declares is checked before it is used (glTF 2.0, sections 3.6 and 5):
# indices are non-negative integers below their array's length (a bool is not an integer, -1 is
# not "the last one"), each attribute's accessor has the type and component type its semantic
# allows, a bufferView lies inside its buffer, an accessor's elements inside its bufferView with
# a stride of 4..252 bytes (a multiple of 4) no shorter than one element, offsets aligned to the
# component size; sparse accessors are refused. Files a glTF names are opened through
# :mod:`.regular` (a plain name beside the model, a regular file, no larger than declared).

#: bytes per component of each glTF componentType (5125: UNSIGNED_INT, indices only here)
COMPONENT_SIZE = {BYTE: 1, UBYTE: 1, SHORT: 2, USHORT: 2, 5125: 4, FLOAT: 4}
COMPONENT_NAME = {BYTE: "BYTE", UBYTE: "UNSIGNED_BYTE", SHORT: "SHORT",
                  USHORT: "UNSIGNED_SHORT", 5125: "UNSIGNED_INT", FLOAT: "FLOAT"}
ELEMENT_TYPES = ("SCALAR", "VEC2", "VEC3", "VEC4", "MAT2", "MAT3", "MAT4")
#: the largest integer any glTF size, offset, count or index may be (int64)
MAX_INT = 2**63 - 1
#: bufferView.byteStride bounds (the schema's minimum, maximum and multipleOf)
MIN_STRIDE, MAX_STRIDE, STRIDE_STEP = 4, 252, 4
#: decoded bytes of a plain glTF per byte of its buffers beyond which primitives that share
#: accessors (to multiply a small buffer) are refused; float32 storage decodes 1:1, normalised
#: bytes 4:1, an attribute shared by the 15 SH coefficients of one splat a few times more
AMPLIFICATION, AMPLIFICATION_FLOOR = 16, 256 * 2**20

# allowed accessor types and component types by semantic: {componentType: normalized} where
# normalized is True (must be normalized), False (must not be) or None (either)
_SH = (("VEC3",), {FLOAT: False})
SEMANTICS: dict[str, tuple[tuple[str, ...], dict[int, bool | None]]] = {
    "POSITION": (("VEC3",), {FLOAT: False}),
    "COLOR_0": (("VEC3", "VEC4"), {FLOAT: False, UBYTE: True, USHORT: True}),
    f"{EXT}:ROTATION": (("VEC4",), {FLOAT: False, BYTE: True, SHORT: True}),
    f"{EXT}:SCALE": (("VEC3",), {FLOAT: False, BYTE: None, SHORT: None}),
    f"{EXT}:OPACITY": (("SCALAR",), {FLOAT: False, UBYTE: True, USHORT: True}),
}
_SH_NAME = re.compile(rf"{re.escape(EXT)}:SH_DEGREE_(0|[1-9][0-9]?)_COEF_(0|[1-9][0-9]?)")


def _rule(name: str) -> tuple[tuple[str, ...], dict[int, bool | None]] | None:
    return _SH if _SH_NAME.fullmatch(name) else SEMANTICS.get(name)


def _show(value: object) -> str:
    """A JSON value for an error line (short: a hostile value may be megabytes long)."""
    text = "true" if value is True else "false" if value is False else "null" \
        if value is None else repr(value) if not isinstance(value, int) \
        else str(value) if abs(value) < 10**30 else f"an integer of {len(str(abs(value)))} digits"
    return text if len(text) <= 40 else text[:37] + "..."


def _kind(value: object) -> str:
    return {dict: "an object", list: "an array", str: "a string", bool: "a boolean",
            int: "an integer", float: "a number", type(None): "null"}.get(type(value),
                                                                          type(value).__name__)


def _int(path: str | Path, value: object, what: str, *, low: int = 0,
         high: int | None = None) -> int:
    """``value`` as an index or size: a JSON integer (not a bool, not 1.0) in low..high."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise FormatError(f"{path}: glTF {what} is {_show(value)}; expected an integer")
    high = MAX_INT if high is None else min(high, MAX_INT)
    if value < low or value > high:
        want = f"{low}..{high}" if high >= low else "none: there are no such entries"
        raise FormatError(f"{path}: glTF {what} is {_show(value)}; expected {want}")
    return value


def _list(path: str | Path, doc: dict, key: str, what: str | None = None) -> list:
    value = doc.get(key, [])
    if not isinstance(value, list):
        raise FormatError(f"{path}: glTF {what or key} is {_kind(value)}; expected an array")
    return value


def _object(path: str | Path, value: object, what: str) -> dict:
    if not isinstance(value, dict):
        raise FormatError(f"{path}: glTF {what} is {_kind(value)}; expected an object")
    return value


def _entry(path: str | Path, doc: dict, key: str, index: object, what: str) -> tuple[int, dict]:
    """(index, object) of ``doc[key][index]``, the index checked to be in range."""
    items = _list(path, doc, key)
    i = _int(path, index, what, high=len(items) - 1)
    return i, _object(path, items[i], f"{key}[{i}]")


def _split_glb(path: str | Path, raw: bytes) -> tuple[dict, memoryview | None]:
    if len(raw) < 20:
        raise FormatError(f"{path}: not a GLB file (shorter than its header)")
    magic, version, length = struct.unpack_from("<III", raw)
    if magic != GLB_MAGIC:
        raise FormatError(f"{path}: not a GLB file (no 'glTF' magic)")
    if version != 2:
        raise FormatError(f"{path}: GLB version {version}; expected 2")
    if length != len(raw):
        raise FormatError(f"{path}: GLB header declares {length:,} bytes, the file has "
                          f"{len(raw):,}")
    doc, binary, at = None, None, 12
    whole = memoryview(raw)  # chunks are views of the file's bytes, never copies
    while at + 8 <= len(raw):
        size, kind = struct.unpack_from("<II", raw, at)
        if at + 8 + size > len(raw):
            raise FormatError(f"{path}: GLB chunk at byte {at} runs past the end of the file")
        body = whole[at + 8:at + 8 + size]
        if kind == JSON_CHUNK and doc is None:
            doc = _json(path, bytes(body))
        elif kind == BIN_CHUNK and binary is None:
            binary = body
        at += 8 + size
    if doc is None:
        raise FormatError(f"{path}: GLB file without a JSON chunk")
    return doc, binary


def _json(path: str | Path, body: bytes) -> dict:
    try:
        doc = json.loads(body.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise FormatError(f"{path}: glTF JSON is not valid: {exc}") from exc
    except RecursionError:
        raise FormatError(f"{path}: glTF JSON is nested too deeply") from None
    if not isinstance(doc, dict):
        raise FormatError(f"{path}: glTF JSON is not an object")
    return doc


def _data_uri(path: Path, i: int, uri: str, length: int) -> bytes:
    """A base64 ``data:`` buffer, its text refused before decoding when it holds more than the
    buffer's byteLength (rounded up to GLB's 4-byte padding)."""
    head, sep, body = uri.partition(",")
    if not sep or not head.endswith(";base64"):
        raise FormatError(f"{path}: glTF buffer {i}: bad data URI (expected "
                          "data:...;base64,...)")
    most = 4 * ((length + (-length) % 4 + 2) // 3)
    if len(body) > most:
        raise FormatError(f"{path}: glTF buffer {i}: data URI of {len(body):,} base64 "
                          f"characters holds more than its byteLength {length:,}")
    try:
        return base64.b64decode(body, validate=True)
    except ValueError as exc:
        raise FormatError(f"{path}: glTF buffer {i}: bad data URI ({exc})") from exc


def _external(path: Path, i: int, uri: str, length: int) -> bytes:
    """A buffer file named by ``uri``: a plain (percent-decoded) name in the model's folder, a
    regular file whose links stay there, no larger than byteLength (plus GLB padding), checked
    before it is read."""
    what = f"glTF buffer {i}"
    target = member_path(path, unquote(uri), what)
    try:
        return read_regular(target, max_bytes=length + (-length) % 4, inside=path.parent,
                            what=f"{what} of {path}")
    except FileNotFoundError:
        raise FormatError(f"{path}: {what}: {uri!r} is not a file beside it") from None
    except PermissionError:
        raise InputError(f"{path}: {what}: cannot read {uri!r} (permission denied)") from None
    except OSError as exc:
        raise FormatError(f"{path}: {what}: cannot read {uri!r} "
                          f"({exc.strerror or exc})") from None


def _buffers(path: Path, doc: dict, glb_bin: memoryview | None) -> list[bytes | memoryview]:
    """Each buffer's bytes, exactly its byteLength (a longer source is cut to it)."""
    out: list[bytes | memoryview] = []
    for i, buf in enumerate(_list(path, doc, "buffers")):
        buf = _object(path, buf, f"buffers[{i}]")
        length = _int(path, buf.get("byteLength"), f"buffers[{i}].byteLength", low=1)
        uri = buf.get("uri")
        if uri is None:
            if glb_bin is None or i != 0:
                raise FormatError(f"{path}: glTF buffer {i} has no uri and is not the first "
                                  "buffer of a GLB file (only that one is its binary chunk)")
            data = glb_bin
        elif not isinstance(uri, str):
            raise FormatError(f"{path}: glTF buffer {i}: uri is {_kind(uri)}; expected a "
                              "string")
        elif uri.startswith("data:"):
            data = _data_uri(path, i, uri, length)
        else:
            data = _external(path, i, uri, length)
        if len(data) < length:
            raise FormatError(f"{path}: glTF buffer {i} holds {len(data):,} bytes, fewer than "
                              f"its byteLength {length:,}")
        out.append(data[:length])
    return out


def _view(path: str | Path, doc: dict, buffers: list, index: object,
          what: str = "bufferView", owner: str = ""
          ) -> tuple[int, bytes | memoryview, int, int, int | None]:
    """(index, buffer bytes, byteOffset, byteLength, byteStride or None) of a bufferView, the
    view checked to lie inside its buffer (``owner``: who names it, for the error line)."""
    v, view = _entry(path, doc, "bufferViews", index, f"{what} index{owner}")
    b = _int(path, view.get("buffer"), f"bufferViews[{v}].buffer", high=len(buffers) - 1)
    start = _int(path, view.get("byteOffset", 0), f"bufferViews[{v}].byteOffset")
    size = _int(path, view.get("byteLength"), f"bufferViews[{v}].byteLength", low=1)
    stride = view.get("byteStride")
    if stride is not None:
        stride = _int(path, stride, f"bufferViews[{v}].byteStride", low=MIN_STRIDE,
                      high=MAX_STRIDE)
        if stride % STRIDE_STEP:
            raise FormatError(f"{path}: glTF bufferViews[{v}].byteStride is {stride}; "
                              f"expected a multiple of {STRIDE_STEP}")
    if start + size > len(buffers[b]):
        raise FormatError(f"{path}: glTF {what} {v} runs past its buffer {b} (bytes "
                          f"{start:,} to {start + size:,} of {len(buffers[b]):,})")
    return v, buffers[b], start, size, stride


def _element_size(kind: str, component: int) -> int:
    """Bytes of one element; matrix columns start on 4-byte boundaries (glTF 3.6.2.4)."""
    if kind.startswith("MAT"):
        n = int(kind[3])
        return n * (n * component + (-n * component) % 4)
    return WIDTH[kind] * component


class _Accessor:
    """One checked accessor: where its ``count`` elements lie (``data`` None: no bufferView)."""

    def __init__(self, index: int, count: int, component: int, kind: str, normalized: bool,
                 data: bytes | memoryview | None = None, offset: int = 0,
                 stride: int = 0) -> None:
        self.index, self.count, self.component, self.kind = index, count, component, kind
        self.normalized, self.data, self.offset, self.stride = normalized, data, offset, stride


def _check_accessor(path: str | Path, doc: dict, buffers: list, index: object, name: str, *,
                    semantic: bool = True, need_data: bool = True) -> _Accessor:
    """The accessor of attribute ``name``, checked as glTF 2.0 requires (and, with
    ``semantic``, its type and component type against what ``name`` allows)."""
    i, acc = _entry(path, doc, "accessors", index, f"accessor index of attribute {name}")
    label = f"accessor {i} ({name})"
    if "sparse" in acc:
        raise FormatError(f"{path}: glTF {label} is sparse; sparse accessors are not supported "
                          "(write the values in full)")
    component = _int(path, acc.get("componentType"), f"{label} componentType")
    if component not in COMPONENT_SIZE:
        raise FormatError(f"{path}: glTF {label} componentType {component} is not a glTF "
                          f"component type (expected one of {sorted(COMPONENT_SIZE)})")
    kind = acc.get("type")
    if kind not in ELEMENT_TYPES:
        raise FormatError(f"{path}: glTF {label} type is {_show(kind)}; expected one of "
                          f"{', '.join(ELEMENT_TYPES)}")
    count = _int(path, acc.get("count"), f"{label} count", low=1)
    normalized = acc.get("normalized", False)
    if not isinstance(normalized, bool):
        raise FormatError(f"{path}: glTF {label} normalized is {_show(normalized)}; expected "
                          "true or false")
    if normalized and component in (FLOAT, 5125):
        raise FormatError(f"{path}: glTF {label} is normalized {COMPONENT_NAME[component]}; "
                          "only integer components other than UNSIGNED_INT may be normalized")
    rule = _rule(name) if semantic else None
    if rule is not None:
        kinds, components = rule
        if kind not in kinds or component not in components or \
                components[component] not in (None, normalized):
            allowed = ", ".join(("normalized " if norm else "") + COMPONENT_NAME[c]
                                for c, norm in components.items())
            got = ("normalized " if normalized else "") + COMPONENT_NAME[component]
            raise FormatError(f"{path}: glTF {label} is {kind} {got}; {name} must be "
                              f"{' or '.join(kinds)} of {allowed}")
    offset = _int(path, acc.get("byteOffset", 0), f"{label} byteOffset")
    if "bufferView" not in acc:
        if need_data:
            raise FormatError(f"{path}: glTF {label} has no bufferView (all-zero attributes "
                              "are not supported)")
        return _Accessor(i, count, component, kind, normalized)
    v, data, start, size, stride = _view(path, doc, buffers, acc["bufferView"],
                                         owner=f" of {label}")
    size_of = COMPONENT_SIZE[component]
    if offset % size_of or (start + offset) % size_of:
        raise FormatError(f"{path}: glTF {label} starts at byte {start + offset:,} of its "
                          f"buffer; expected a multiple of its {size_of}-byte components")
    element = _element_size(kind, size_of)
    if stride is not None and stride < element:
        raise FormatError(f"{path}: glTF bufferViews[{v}].byteStride {stride} is less than "
                          f"the {element} bytes of each element of {label} ({kind} "
                          f"{COMPONENT_NAME[component]})")
    stride = stride or element
    end = offset + stride * (count - 1) + element
    if end > size:
        raise FormatError(f"{path}: glTF {label}: {count:,} elements of {element} bytes every "
                          f"{stride} from byte {offset:,} end at byte {end:,}, past its "
                          f"bufferView {v} of {size:,} bytes")
    return _Accessor(i, count, component, kind, normalized, data, start + offset, stride)


def _values(acc: _Accessor) -> np.ndarray:
    """(count, width) values of a checked accessor: float32 as stored, integers as float64
    (normalised ones scaled to -1..1 / 0..1)."""
    dtype = np.dtype(COMPONENT[acc.component])
    width = WIDTH[acc.kind]
    view = np.ndarray((acc.count, width), dtype=dtype, buffer=acc.data, offset=acc.offset,
                      strides=(acc.stride, dtype.itemsize))
    if acc.component == FLOAT:  # float32 stays float32: a read-only view, copied once later
        return view.astype(np.float32, copy=False)
    if not acc.normalized:
        return view.astype(np.float64)
    return NORMALISE[acc.component](view.astype(np.float64))


def _accessor(path: Path, doc: dict, buffers: list, index: int, name: str) -> np.ndarray:
    """(count, width) values of accessor ``index`` of attribute ``name``, checked."""
    return _values(_check_accessor(path, doc, buffers, index, name))


def _sh_degree(path: str | Path, attrs: dict) -> int:
    """The SH degree a primitive's attributes declare; every coefficient of degrees 1 to it
    must be there (the extension forbids partial degrees): a missing one is named."""
    prefix = f"{EXT}:SH_DEGREE_"
    degree = 0
    for name in attrs:
        if not name.startswith(prefix):
            continue
        m = _SH_NAME.fullmatch(name)
        ell = int(m.group(1)) if m else -1
        if m is None or ell > 3 or int(m.group(2)) > 2 * ell:
            raise FormatError(f"{path}: {EXT} attribute {_show(name)} is not an SH coefficient "
                              "of degrees 0 to 3 (SH_DEGREE_l_COEF_n, n from 0 to 2l)")
        degree = max(degree, ell)
    missing = [n for n in _sh_names(degree) if n not in attrs]
    if missing:
        raise FormatError(f"{path}: {EXT} primitive has SH degree {degree} attributes but lacks "
                          f"{', '.join(missing)} (every coefficient of degrees 1 to {degree} "
                          "is required)")
    return degree


def splat_primitives(path: str | Path, doc: dict) -> list[dict]:
    """The primitives carrying the extension, checked against its required fields."""
    prims = []
    for m, mesh in enumerate(_list(path, doc, "meshes")):
        mesh = _object(path, mesh, f"meshes[{m}]")
        for j, p in enumerate(_list(path, mesh, "primitives", f"meshes[{m}].primitives")):
            p = _object(path, p, f"meshes[{m}].primitives[{j}]")
            ext = _object(path, p.get("extensions", {}),
                          f"meshes[{m}].primitives[{j}].extensions")
            if EXT in ext:
                _object(path, ext[EXT], f"meshes[{m}].primitives[{j}] {EXT} extension")
                _object(path, p.get("attributes"), f"meshes[{m}].primitives[{j}].attributes")
                prims.append(p)
    if not prims:
        raise FormatError(f"{path}: no glTF primitive with the {EXT} extension")
    used = _list(path, doc, "extensionsUsed")  # lists of strings (read_document)
    required = _list(path, doc, "extensionsRequired")
    if EXT not in used:
        raise FormatError(f"{path}: {EXT} is used but not listed in extensionsUsed")
    unknown = [e for e in required if e != EXT and e not in SPZ_EXTS]
    if unknown:
        raise FormatError(f"{path}: glTF requires extension(s) {', '.join(unknown)}, which "
                          "this reader does not support")
    for p in prims:
        if _int(path, p.get("mode", 4), f"{EXT} primitive mode") != 0:
            raise FormatError(f"{path}: a {EXT} primitive must have mode 0 (POINTS)")
        needed = ("POSITION",) if _spz_view(path, p) is not None else (
            "POSITION", f"{EXT}:ROTATION", f"{EXT}:SCALE", f"{EXT}:OPACITY",
            f"{EXT}:SH_DEGREE_0_COEF_0")
        missing = [a for a in needed if a not in p["attributes"]]
        if missing:
            raise FormatError(f"{path}: {EXT} primitive lacks attribute(s) {', '.join(missing)}")
        _sh_degree(path, p["attributes"])
    for k, node in enumerate(_list(path, doc, "nodes")):
        node = _object(path, node, f"nodes[{k}]")
        if any(key in node for key in ("matrix", "translation", "rotation", "scale")):
            raise FormatError(f"{path}: glTF node transforms are not supported (bake them into "
                              "the splats first)")
    return prims


def _spz_view(path: str | Path, prim: dict) -> int | None:
    """The bufferView of the primitive's SPZ compression extension (None: not compressed)."""
    nested = prim["extensions"][EXT]
    nested = nested.get("extensions") if isinstance(nested, dict) else None
    for name in SPZ_EXTS:
        if isinstance(nested, dict) and name in nested:
            view = nested[name].get("bufferView") if isinstance(nested[name], dict) else None
            if not isinstance(view, int) or isinstance(view, bool):
                raise FormatError(f"{path}: glTF {name} needs an integer bufferView (got "
                                  f"{_show(view)})")
            return view
    return None


def _counts(path: str | Path, doc: dict, buffers: list, prim: dict, *,
            compressed: bool) -> dict[str, _Accessor]:
    """Every attribute of ``prim`` checked (an SPZ-compressed primitive's accessors hold no
    data: only their index and count are checked) and, uncompressed, of one count."""
    checked = {name: _check_accessor(path, doc, buffers, index, name, semantic=not compressed,
                                     need_data=not compressed and name != "COLOR_0"
                                     and _rule(name) is not None)
               for name, index in prim["attributes"].items()}
    if not compressed:
        counts = {name: acc.count for name, acc in checked.items()}
        if len(set(counts.values())) > 1:
            first = counts["POSITION"]
            other = next(name for name, c in counts.items() if c != first)
            raise FormatError(f"{path}: {EXT} attributes have different counts (POSITION "
                              f"{first:,}, {other} {counts[other]:,}); every attribute of a "
                              "primitive needs the same count")
    return checked


def _spz_head(blob: bytes | memoryview) -> bytes | None:
    """The first 16 inflated bytes of a gzip'd SPZ blob (None when they cannot be had: the
    SPZ reader then says what is wrong)."""
    try:
        return zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(blob, spz.HEADER.size)
    except zlib.error:
        return None


def _spz_fields(path: Path, doc: dict, buffers: list, prim: dict, index: int,
                attrs: dict[str, _Accessor]) -> SplatFields:
    """The splats of an SPZ-compressed primitive: the gzip'd SPZ blob in its bufferView,
    packed in glTF's LUF frame (the extension's specification), decoded to PLY space. The SPZ
    header is inflated first: a splat count other than the accessors' is refused before the
    rest is; :mod:`.spz` bounds the inflation itself (the declared size against the blob's
    size and the memory, the output against the declared size)."""
    _, data, start, size, _ = _view(path, doc, buffers, index, "SPZ bufferView")
    blob = data[start:start + size]
    head = _spz_head(blob)
    declared = attrs["POSITION"].count
    if head is not None and len(head) == spz.HEADER.size:
        n = spz.parse_header(path, head)["count"]
        for name, acc in attrs.items():
            if acc.count != n:
                raise FormatError(f"{path}: glTF {name} accessor count {acc.count} differs "
                                  f"from the {n} splats of its SPZ data")
    raw = spz.gunzip_blob(path, blob)
    fields, _ = spz.decode(raw, path, spz.LUF)
    del raw
    if declared != fields.count:
        raise FormatError(f"{path}: glTF POSITION accessor count {declared} differs from the "
                          f"{fields.count} splats of its SPZ data")
    return fields


def _fields(path: Path, doc: dict, buffers: list, prim: dict,
            checked: dict[str, _Accessor]) -> SplatFields:
    """The splats of one primitive whose attributes ``checked`` are (:func:`_counts`)."""
    attrs = prim["attributes"]
    view = _spz_view(path, prim)
    if view is not None:
        return _spz_fields(path, doc, buffers, prim, view, checked)

    def get(name: str) -> np.ndarray:
        return _values(checked[name])

    degree = _sh_degree(path, attrs)
    positions = get("POSITION")
    n = len(positions)
    xyzw = get(f"{EXT}:ROTATION")
    scale = get(f"{EXT}:SCALE")
    opacity = get(f"{EXT}:OPACITY")[:, 0]
    dc = get(f"{EXT}:SH_DEGREE_0_COEF_0")
    names = _sh_names(degree)
    rest = np.empty((n, 3, len(names)), dtype=np.float32)
    for j, name in enumerate(names):
        rest[:, :, j] = get(name)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        scale_log = np.log(scale.astype(np.float64))
        p = np.clip(opacity.astype(np.float64), OPACITY_EPS, 1 - OPACITY_EPS)
        logit = np.log(p) - np.log1p(-p)
    wxyz = np.stack([xyzw[:, 3], xyzw[:, 0], xyzw[:, 1], xyzw[:, 2]], axis=1)
    k = SH_COEFFS[degree]
    rest *= SH_FLIP[:k]
    return SplatFields(positions=positions * FLIP, scale_log=scale_log.astype(np.float32),
                       rotation=_unturn(wxyz).astype(np.float32),
                       opacity=logit.astype(np.float32), sh_dc=dc.astype(np.float32),
                       sh_rest=rest)


def _check_amplification(path: Path, buffers: list,
                         plain: list[tuple[dict, dict[str, _Accessor]]]) -> None:
    """Refuse plain primitives whose decoded splats would be many times the bytes of the
    buffers (primitives sharing one accessor to multiply a small file)."""
    stored = sum(len(b) for b in buffers)
    total = sum(checked["POSITION"].count * 4 * (14 + 3 * SH_COEFFS[_sh_degree(path, attrs)])
                for attrs, checked in plain)
    if total > AMPLIFICATION * stored + AMPLIFICATION_FLOOR:
        raise FormatError(f"{path}: glTF primitives declare {total / 2**20:,.0f} MiB of splats "
                          f"from {stored / 2**20:,.1f} MiB of buffers (primitives sharing "
                          "accessors?); refused")


def read_document(path: str | Path) -> tuple[dict, list[bytes | memoryview]]:
    """The glTF JSON and its buffers (each exactly its byteLength), every file it names read
    through :func:`.regular.read_regular`."""
    path = Path(path)
    raw = read_regular(path)
    if path.name.lower().endswith(".glb"):
        doc, glb_bin = _split_glb(path, raw)
    else:
        doc, glb_bin = _json(path, raw), None
    return _check_document(path, doc), _buffers(path, doc, glb_bin)


def _check_document(path: Path, doc: dict) -> dict:
    """The checks of the JSON that :func:`read_document` runs before reading buffers."""
    _object(path, doc.get("asset", {}), "asset")
    for key in ("extensionsUsed", "extensionsRequired"):
        if not all(isinstance(e, str) for e in _list(path, doc, key)):
            raise FormatError(f"{path}: glTF {key} holds a non-string; expected extension "
                              "names")
    return doc


def _head_document(path: Path, head: bytes, size: int, file: Path | None) -> dict | None:
    """The glTF JSON from the file's first bytes ``head`` (the whole JSON of ``file`` when
    ``head`` does not hold it), checked like :func:`_split_glb` against the file ``size``;
    None when neither holds it."""
    if not path.name.lower().endswith(".glb"):
        if size <= len(head):
            return _json(path, head[:size])
        return None if file is None else _json(path, read_regular(file))
    if len(head) < 20:
        raise FormatError(f"{path}: not a GLB file (shorter than its header)")
    magic, version, length = struct.unpack_from("<III", head)
    if magic != GLB_MAGIC:
        raise FormatError(f"{path}: not a GLB file (no 'glTF' magic)")
    if version != 2:
        raise FormatError(f"{path}: GLB version {version}; expected 2")
    if length != size:
        raise FormatError(f"{path}: GLB header declares {length:,} bytes, the file has "
                          f"{size:,}")
    doc, at = None, 12
    while at + 8 <= size:
        if at + 8 > len(head):
            return doc
        chunk, kind = struct.unpack_from("<II", head, at)
        if at + 8 + chunk > size:
            raise FormatError(f"{path}: GLB chunk at byte {at} runs past the end of the file")
        if kind == JSON_CHUNK and doc is None:
            if at + 8 + chunk > len(head):
                if file is None:
                    return None
                with open_regular(file) as fh:
                    fh.seek(at + 8)
                    doc = _json(path, fh.read(chunk))
            else:
                doc = _json(path, bytes(head[at + 8:at + 8 + chunk]))
        at += 8 + chunk
    if doc is None:
        raise FormatError(f"{path}: GLB file without a JSON chunk")
    return doc


def declared_splats(path: str | Path, head: bytes, size: int,
                    file: Path | None = None) -> tuple[int, int] | None:
    """(splats, SH degree) a glTF declares: the POSITION accessors' counts of its
    ``KHR_gaussian_splatting`` primitives, from the JSON alone (no buffer is read): the file's
    first bytes ``head`` of ``size``, or ``file`` when the JSON lies beyond them. None when the
    JSON cannot be had (an archive member whose JSON passes ``head``). Raises the loader's
    FormatError lines for a JSON it would refuse."""
    path = Path(path)
    doc = _head_document(path, head, size, file)
    if doc is None:
        return None
    prims = splat_primitives(path, _check_document(path, doc))
    total = degree = 0
    for p in prims:
        i, acc = _entry(path, doc, "accessors", p["attributes"]["POSITION"],
                        "accessor index of attribute POSITION")
        total += _int(path, acc.get("count"), f"accessor {i} (POSITION) count", low=1)
        degree = max(degree, _sh_degree(path, p["attributes"]))
    return total, degree


def read_model(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    path = Path(path)
    doc, buffers = read_document(path)
    prims = splat_primitives(path, doc)
    checked = [_counts(path, doc, buffers, p, compressed=_spz_view(path, p) is not None)
               for p in prims]  # every primitive checked before any is decoded
    _check_amplification(path, buffers, [(p["attributes"], c) for p, c in zip(
        prims, checked, strict=True) if _spz_view(path, p) is None])
    parts = [_fields(path, doc, buffers, p, c) for p, c in zip(prims, checked, strict=True)]
    if len({f.sh_rest.shape[2] for f in parts}) > 1:
        raise FormatError(f"{path}: {EXT} primitives with different SH degrees")
    f = parts[0] if len(parts) == 1 else SplatFields(*(
        np.concatenate([getattr(p, a) for p in parts]) for a in (
            "positions", "scale_log", "rotation", "opacity", "sh_dc", "sh_rest")))
    del parts, buffers  # the table to_model fills is the copy the model is built from
    used = ", ".join(doc.get("extensionsUsed", []))
    return to_model(f, path, [f"read from glTF ({used}) by splatdeform"],
                    drop_nonfinite=drop_nonfinite)


# --------------------------------------------------------------------------------------------
# writing


def _attributes(f: SplatFields) -> list[tuple[str, int, str, dict, Callable[[], np.ndarray]]]:
    """(name, width, dtype, accessor extras, make) per attribute: ``make()`` builds that one
    (N, width) array when its bytes are written (one attribute's temporaries at a time)."""
    k = f.sh_rest.shape[2]
    degree = {c: d for d, c in SH_COEFFS.items()}[k]

    def color() -> np.ndarray:
        rgb = np.clip(np.round(dc_to_color(f.sh_dc) * 255), 0, 255)
        return np.concatenate([rgb, np.round(sigmoid(f.opacity) * 255)[:, None]], axis=1) \
            .astype("u1")

    def rotation() -> np.ndarray:
        wxyz = _turn(normalised_quaternions(f.rotation))
        return np.stack([wxyz[:, 1], wxyz[:, 2], wxyz[:, 3], wxyz[:, 0]], axis=1).astype("<f4")

    def sh(j: int) -> Callable[[], np.ndarray]:
        return lambda: (f.sh_rest[:, :, j] * SH_FLIP[j]).astype("<f4")

    return [
        ("POSITION", 3, "<f4", {}, lambda: (f.positions * FLIP).astype("<f4")),
        ("COLOR_0", 4, "u1", {"normalized": True}, color),
        (f"{EXT}:ROTATION", 4, "<f4", {}, rotation),
        (f"{EXT}:SCALE", 3, "<f4", {}, lambda: np.exp(f.scale_log.astype(np.float64))
         .astype("<f4")),
        (f"{EXT}:OPACITY", 1, "<f4", {}, lambda: sigmoid(f.opacity).astype("<f4")[:, None]),
        (f"{EXT}:SH_DEGREE_0_COEF_0", 3, "<f4", {}, lambda: f.sh_dc.astype("<f4")),
        *((name, 3, "<f4", {}, sh(j)) for j, name in enumerate(_sh_names(degree))),
    ]


def _document(f: SplatFields) -> tuple[dict, Iterator[bytes | memoryview]]:
    """The glTF JSON document and the binary buffer's pieces (each attribute built and
    yielded in turn, 4-byte aligned), so a write never holds the whole buffer."""
    n = f.count
    attributes = _attributes(f)
    positions = attributes[0][4]()
    accessors, views, at = [], [], 0
    for i, (name, width, dtype, extra, _) in enumerate(attributes):
        size = n * width * np.dtype(dtype).itemsize
        views.append({"buffer": 0, "byteOffset": at, "byteLength": size, "target": 34962})
        acc = {"bufferView": i, "componentType": FLOAT if dtype == "<f4" else UBYTE,
               "count": n, "type": {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[width], **extra}
        if name == "POSITION":
            acc["min"] = positions.min(axis=0).tolist()
            acc["max"] = positions.max(axis=0).tolist()
        accessors.append(acc)
        at += size + (-size) % 4
    doc = {"asset": {"version": "2.0", "generator": "splatdeform"},
           "extensionsUsed": [EXT], "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{
               "attributes": {a[0]: i for i, a in enumerate(attributes)}, "mode": 0,
               "extensions": {EXT: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display",
                                    "sortingMethod": "cameraDistance",
                                    "projection": "perspective"}}}]}],
           "accessors": accessors, "bufferViews": views,
           "buffers": [{"byteLength": at}]}

    def pieces() -> Iterator[bytes | memoryview]:
        for i, (_, _, _, _, make) in enumerate(attributes):
            values = np.ascontiguousarray(positions if i == 0 else make())
            yield memoryview(values).cast("B")
            yield b"\0" * ((-values.nbytes) % 4)
            del values

    return doc, pieces()


def write_model(model: PointModel, path: Path, stream) -> None:
    f = fields_of(model, path, Path(path).suffix.lower())
    if f.count:  # the linear scale is stored: exp(scale_log) must fit float32
        with np.errstate(over="ignore"):
            top = np.exp(np.array([np.nanmax(f.scale_log.astype(np.float64))]))
        check_fits("scale (exp of scale_log)", top, np.float32, "glTF")
    note_lossy(path, "glTF", None, model)
    doc, pieces = _document(f)
    if Path(path).suffix.lower() == ".gltf":
        doc["buffers"][0]["uri"] = ("data:application/octet-stream;base64,"
                                    + base64.b64encode(b"".join(pieces)).decode("ascii"))
        stream.write(json.dumps(doc, separators=(",", ":")).encode("utf-8"))
        return
    write_glb(stream, doc, pieces)


def write_glb(stream, doc: dict, pieces: Iterable[bytes | memoryview]) -> None:
    """The GLB container: header, JSON chunk (space padded), BIN chunk of ``pieces`` (whose
    total is the document's ``buffers[0].byteLength``, a multiple of 4)."""
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * ((-len(text)) % 4)
    size = doc["buffers"][0]["byteLength"]
    total = 12 + 8 + len(text) + 8 + size
    stream.write(struct.pack("<III", GLB_MAGIC, 2, total))
    stream.write(struct.pack("<II", len(text), JSON_CHUNK) + text)
    stream.write(struct.pack("<II", size, BIN_CHUNK))
    for piece in pieces:
        stream.write(piece)
