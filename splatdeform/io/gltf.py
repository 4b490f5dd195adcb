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
import struct
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..model import PointModel
from . import spz
from .splat_model import to_model
from .splats import (
    SH_COEFFS,
    SplatFields,
    dc_to_color,
    fields_of,
    normalised_quaternions,
    note_lossy,
    read_bytes,
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


def _split_glb(path: str | Path, raw: bytes) -> tuple[dict, bytes | None]:
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
    while at + 8 <= len(raw):
        size, kind = struct.unpack_from("<II", raw, at)
        body = raw[at + 8:at + 8 + size]
        if len(body) != size:
            raise FormatError(f"{path}: GLB chunk at byte {at} runs past the end of the file")
        if kind == JSON_CHUNK and doc is None:
            doc = _json(path, body)
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
    if not isinstance(doc, dict):
        raise FormatError(f"{path}: glTF JSON is not an object")
    return doc


def _buffers(path: Path, doc: dict, glb_bin: bytes | None) -> list[bytes]:
    out = []
    for i, buf in enumerate(doc.get("buffers", [])):
        uri = buf.get("uri")
        if uri is None:
            if glb_bin is None:
                raise FormatError(f"{path}: glTF buffer {i} has no uri and there is no GLB "
                                  "binary chunk")
            out.append(glb_bin)
        elif uri.startswith("data:"):
            try:
                out.append(base64.b64decode(uri.split(",", 1)[1], validate=True))
            except (IndexError, ValueError) as exc:
                raise FormatError(f"{path}: glTF buffer {i}: bad data URI") from exc
        else:
            target = (path.parent / uri).resolve()
            if "/" in uri or "\\" in uri or not target.is_file():
                raise FormatError(f"{path}: glTF buffer {i}: {uri!r} is not a file beside it")
            out.append(read_bytes(target))
        if len(out[-1]) < int(buf.get("byteLength", 0)):
            raise FormatError(f"{path}: glTF buffer {i} is shorter than its byteLength")
    return out


def _accessor(path: Path, doc: dict, buffers: list[bytes], index: int, name: str) -> np.ndarray:
    """(count, width) values of accessor ``index``: float32 as stored, normalised integers
    scaled to float64."""
    try:
        acc = doc["accessors"][index]
        view = doc["bufferViews"][acc["bufferView"]]
        data = buffers[view["buffer"]]
        kind, width = acc["componentType"], WIDTH[acc["type"]]
        dtype = np.dtype(COMPONENT[kind])
        count = int(acc["count"])
    except (KeyError, IndexError, TypeError) as exc:
        raise FormatError(f"{path}: glTF attribute {name}: accessor {index} is incomplete "
                          f"or of an unsupported type ({exc})") from exc
    start = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
    stride = int(view.get("byteStride", 0)) or dtype.itemsize * width
    end = start + stride * (count - 1) + dtype.itemsize * width if count else start
    if start < 0 or end > int(view.get("byteOffset", 0)) + int(view["byteLength"]) \
            or end > len(data):
        raise FormatError(f"{path}: glTF attribute {name}: {count:,} values run past their "
                          "buffer view")
    view = np.ndarray((count, width), dtype=dtype, buffer=data, offset=start,
                      strides=(stride, dtype.itemsize))
    if kind == FLOAT:  # float32 stays float32: a read-only view of the buffer, copied once later
        return view.astype(np.float32, copy=False)
    if not acc.get("normalized"):
        raise FormatError(f"{path}: glTF attribute {name}: integer values must be normalized")
    return NORMALISE[kind](view.astype(np.float64))


def splat_primitives(path: str | Path, doc: dict) -> list[dict]:
    """The primitives carrying the extension, checked against its required fields."""
    prims = [p for mesh in doc.get("meshes", []) for p in mesh.get("primitives", [])
             if EXT in p.get("extensions", {})]
    if not prims:
        raise FormatError(f"{path}: no glTF primitive with the {EXT} extension")
    if EXT not in doc.get("extensionsUsed", []):
        raise FormatError(f"{path}: {EXT} is used but not listed in extensionsUsed")
    unknown = [e for e in doc.get("extensionsRequired", []) if e != EXT and e not in SPZ_EXTS]
    if unknown:
        raise FormatError(f"{path}: glTF requires extension(s) {', '.join(unknown)}, which "
                          "this reader does not support")
    for p in prims:
        if p.get("mode", 4) != 0:
            raise FormatError(f"{path}: a {EXT} primitive must have mode 0 (POINTS)")
        needed = ("POSITION",) if _spz_view(path, p) is not None else (
            "POSITION", f"{EXT}:ROTATION", f"{EXT}:SCALE", f"{EXT}:OPACITY",
            f"{EXT}:SH_DEGREE_0_COEF_0")
        missing = [a for a in needed if a not in p.get("attributes", {})]
        if missing:
            raise FormatError(f"{path}: {EXT} primitive lacks attribute(s) {', '.join(missing)}")
    for node in doc.get("nodes", []):
        if any(k in node for k in ("matrix", "translation", "rotation", "scale")):
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
                                  f"{view!r})")
            return view
    return None


def _spz_fields(path: Path, doc: dict, buffers: list[bytes], prim: dict,
                index: int) -> SplatFields:
    """The splats of an SPZ-compressed primitive: the gzip'd SPZ blob in its bufferView,
    packed in glTF's LUF frame (the extension's specification), decoded to PLY space."""
    try:
        view = doc["bufferViews"][index]
        data = buffers[view["buffer"]]
        start, size = int(view.get("byteOffset", 0)), int(view["byteLength"])
        count = doc["accessors"][prim["attributes"]["POSITION"]].get("count")
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise FormatError(f"{path}: glTF SPZ bufferView {index} is incomplete ({exc})") from exc
    if start < 0 or size < 0 or start + size > len(data):
        raise FormatError(f"{path}: glTF SPZ bufferView {index} runs past its buffer")
    raw = spz.gunzip_blob(path, bytes(data[start:start + size]))
    fields, info = spz.decode(raw, path, spz.LUF)
    if count is not None and count != fields.count:
        raise FormatError(f"{path}: glTF POSITION accessor count {count} differs from the "
                          f"{fields.count} splats of its SPZ data")
    return fields


def _fields(path: Path, doc: dict, buffers: list[bytes], prim: dict) -> SplatFields:
    attrs = prim["attributes"]
    view = _spz_view(path, prim)
    if view is not None:
        return _spz_fields(path, doc, buffers, prim, view)

    def get(name: str) -> np.ndarray:
        return _accessor(path, doc, buffers, attrs[name], name)

    degree = 0
    while degree < 3 and all(n in attrs for n in _sh_names(degree + 1)):
        degree += 1
    positions = get("POSITION")
    n = len(positions)
    xyzw = get(f"{EXT}:ROTATION")
    scale = get(f"{EXT}:SCALE")
    opacity = get(f"{EXT}:OPACITY")[:, 0]
    dc = get(f"{EXT}:SH_DEGREE_0_COEF_0")
    parts = [get(name) for name in _sh_names(degree)]
    if any(len(a) != n for a in (xyzw, scale, opacity, dc, *parts)):
        raise FormatError(f"{path}: {EXT} attributes have different counts")
    rest = np.empty((n, 3, len(parts)), dtype=np.float32)
    for j, part in enumerate(parts):
        rest[:, :, j] = part
    with np.errstate(divide="ignore", invalid="ignore"):
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


def read_document(path: str | Path) -> tuple[dict, list[bytes]]:
    path = Path(path)
    raw = read_bytes(path)
    if path.suffix.lower() == ".glb":
        doc, glb_bin = _split_glb(path, raw)
    else:
        doc, glb_bin = _json(path, raw), None
    return doc, _buffers(path, doc, glb_bin)


def read_model(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    path = Path(path)
    doc, buffers = read_document(path)
    parts = [_fields(path, doc, buffers, p) for p in splat_primitives(path, doc)]
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
