"""E57 (ASTM E2807) files <-> :class:`PointModel`, through pye57 (libE57Format).

Terrestrial laser scanners exchange E57: several scans in one file, each with its pose (a
rotation quaternion and a translation from the scan's own frame to the file's world frame)
and per-point fields (cartesian or spherical coordinates, intensity, colour, row/column and
return indices, time stamps, invalid-state flags).

Reading keeps every scan whole (:class:`E57Source`): its header (name, guid, description,
sensor, acquisition times, pose, index/intensity/colour limits, every other node, as its
element tree) and its point records, every field of its prototype at its own type (scaled
integers as their raw integers). The model's positions are the valid points of every scan with
its pose applied: one world frame, so a deformation applies to all scans at once. A point whose
``cartesianInvalidState`` (or ``sphericalInvalidState``) is not 0 has no position: it is
carried in its scan's records, never deformed, selected or rendered, and written back as read.
Colours are the scans' colour fields scaled to 8 bits by their limits.

Writing an E57-read model writes each scan as a scan again: its header tree (pose unchanged;
``cartesianBounds`` recomputed), its prototype (types, scales, precision kept; minimum and
maximum widened where deformed coordinates need it) and its records, the deformed positions
turned back into the scan's own frame by the inverse of its pose (spherical scans get range,
azimuth and elevation back). Points that did not move keep their raw values exactly. 2D images
(``images2D``) are not kept. A model from another format is written as one scan (double
precision cartesian coordinates, colour and intensity when the model has them, no pose).

Not streamable: over the memory budget an E57 file is refused (the probe reads the file's XML
section for the declared point counts).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..model import PlyElementData, PlyProperty, PlySource, PointModel, classify
from .inflate import check_declared
from .ply_format import TYPE_NAMES
from .regular import open_regular

SIGNATURE = b"ASTM-E57"
HEADER_SIZE = 48
MAX_XML_BYTES = 64 << 20   # the XML section (scan headers and prototypes) held at most
CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
COLOURS = ("colorRed", "colorGreen", "colorBlue")


def _libe57():
    from pye57 import libe57

    return libe57


# ---- the file header and its XML (the probe; no pye57) ----------------------------------------

@dataclass(frozen=True)
class E57Layout:
    """What the 48-byte file header says: version, the physical length (= the file size),
    where the XML section starts and its logical length, the page size."""

    version: tuple[int, int]
    length: int
    xml_offset: int
    xml_length: int
    page_size: int


def check_header(name, head: bytes, size: int) -> E57Layout:
    """The file header checked against the file size (one FormatError line naming ``name``)."""
    if len(head) < HEADER_SIZE or head[:8] != SIGNATURE:
        raise FormatError(f"{name}: not an E57 file (it does not start with 'ASTM-E57')")
    major, minor, length, xml_offset, xml_length, page = struct.unpack_from("<IIQQQQ", head, 8)
    if length != size:
        raise FormatError(f"{name}: corrupt E57 header: physical length {length:,} != the file "
                          f"size {size:,}")
    if page < 64 or page & (page - 1) or page > 1 << 20:
        raise FormatError(f"{name}: corrupt E57 header: page size {page} (expected a power of "
                          "two, 64 bytes to 1 MiB)")
    if not HEADER_SIZE <= xml_offset < size or xml_length > size:
        raise FormatError(f"{name}: corrupt E57 header: XML section at {xml_offset:,} of "
                          f"{xml_length:,} bytes, outside the {size:,}-byte file")
    if xml_length > MAX_XML_BYTES:
        raise FormatError(f"{name}: E57 XML section of {xml_length:,} bytes (at most "
                          f"{MAX_XML_BYTES:,} read)")
    return E57Layout((major, minor), length, xml_offset, xml_length, page)


def read_xml(f, layout: E57Layout) -> bytes:
    """The logical bytes of the XML section (each physical page ends with a 4-byte CRC)."""
    data = layout.page_size - 4
    out = bytearray()
    page, at = divmod(layout.xml_offset, layout.page_size)
    while len(out) < layout.xml_length:
        f.seek(page * layout.page_size + at)
        chunk = f.read(data - at)
        if not chunk:
            break
        out += chunk
        page, at = page + 1, 0
    return bytes(out[:layout.xml_length])


_POINTS = re.compile(rb'<points\b[^>]*\brecordCount="(\d+)"')


def declared_points(xml: bytes) -> list[int]:
    """The record counts of the scans' ``points`` compressed vectors, in file order."""
    return [int(m.group(1)) for m in _POINTS.finditer(xml)]


def file_points(path: str | Path) -> list[int]:
    """Each scan's declared point count, from the file's header and XML (no pye57)."""
    with open_regular(path) as f:
        size = f.seek(0, 2)
        f.seek(0)
        layout = check_header(path, f.read(HEADER_SIZE), size)
        return declared_points(read_xml(f, layout))


# ---- the element tree of a scan header ------------------------------------------------------

def _capture(node):
    """A scan header node as a plain tree: (kind, name, values..., children); None for the
    point data (a compressed vector) and blobs."""
    lib = _libe57()
    kind, name = node.type(), node.elementName()
    t = lib.NodeType
    if kind == t.E57_STRUCTURE:
        s = lib.StructureNode(node)
        return ("S", name, [c for c in (_capture(s.get(i)) for i in range(s.childCount())) if c])
    if kind == t.E57_VECTOR:
        v = lib.VectorNode(node)
        return ("V", name, bool(v.allowHeteroChildren()),
                [c for c in (_capture(v.get(i)) for i in range(v.childCount())) if c])
    if kind == t.E57_INTEGER:
        n = lib.IntegerNode(node)
        return ("I", name, n.value(), n.minimum(), n.maximum())
    if kind == t.E57_SCALED_INTEGER:
        n = lib.ScaledIntegerNode(node)
        return ("SI", name, n.rawValue(), n.minimum(), n.maximum(), n.scale(), n.offset())
    if kind == t.E57_FLOAT:
        n = lib.FloatNode(node)
        return ("F", name, n.value(), n.precision() == lib.FloatPrecision.E57_SINGLE,
                n.minimum(), n.maximum())
    if kind == t.E57_STRING:
        return ("T", name, lib.StringNode(node).value())
    return None


def _build(imf, item):
    """A node of the image file ``imf`` from a :func:`_capture` tree."""
    lib = _libe57()
    kind = item[0]
    if kind == "S":
        node = lib.StructureNode(imf)
        for child in item[2]:
            node.set(child[1], _build(imf, child))
        return node
    if kind == "V":
        node = lib.VectorNode(imf, item[2])
        for child in item[3]:
            node.append(_build(imf, child))
        return node
    if kind == "I":
        return lib.IntegerNode(imf, item[2], item[3], item[4])
    if kind == "SI":
        return lib.ScaledIntegerNode(imf, int(item[2]), int(item[3]), int(item[4]), item[5],
                                     item[6])
    if kind == "F":
        precision = lib.FloatPrecision.E57_SINGLE if item[3] else lib.FloatPrecision.E57_DOUBLE
        return lib.FloatNode(imf, item[2], precision, item[4], item[5])
    return lib.StringNode(imf, item[2])


def _child(tree, name: str):
    return next((c for c in tree[2] if c[1] == name), None) if tree and tree[0] == "S" else None


def _value(tree, *path: str, default=None):
    for name in path:
        tree = _child(tree, name)
    return default if tree is None else tree[2]


# ---- scans --------------------------------------------------------------------------------

@dataclass
class E57Field:
    """One field of a scan's point prototype: kind ('I' integer, 'SI' scaled integer, stored
    as its raw integers; 'F' float), its minimum and maximum (raw for 'SI'), scale/offset
    ('SI'), single precision ('F')."""

    name: str
    kind: str
    minimum: float
    maximum: float
    scale: float = 1.0
    offset: float = 0.0
    single: bool = False

    @property
    def dtype(self) -> np.dtype:
        if self.kind == "F":
            return np.dtype("<f4" if self.single else "<f8")
        for code in ("<u1", "<i1", "<u2", "<i2"):
            info = np.iinfo(code)
            if info.min <= self.minimum and self.maximum <= info.max:
                return np.dtype(code)
        # pye57's buffers take 8, 16 and 64-bit integers, the latter as C long long only
        # (a numpy int64 says 'l', which its binding reads as 32-bit values)
        return np.dtype(np.longlong)

    def values(self, raw: np.ndarray) -> np.ndarray:
        """The field's values (scaled integers scaled) as float64 or its integers."""
        if self.kind == "SI":
            return raw.astype(np.float64) * self.scale + self.offset
        return raw


@dataclass
class E57Scan:
    """One scan: its header tree (without the points), prototype fields, records (M,) (every
    point, valid or not) and ``valid`` (M,) bool (the points the model holds)."""

    header: tuple
    fields: list[E57Field]
    records: np.ndarray
    valid: np.ndarray

    @property
    def name(self) -> str:
        return str(_value(self.header, "name", default=""))

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) the pose's rotation (identity without a pose)."""
        q = [_value(self.header, "pose", "rotation", k, default=d)
             for k, d in (("w", 1.0), ("x", 0.0), ("y", 0.0), ("z", 0.0))]
        return quaternion_matrix(np.asarray(q, dtype=np.float64))

    @property
    def translation(self) -> np.ndarray:
        return np.asarray([_value(self.header, "pose", "translation", k, default=0.0)
                           for k in "xyz"], dtype=np.float64)

    @property
    def spherical(self) -> bool:
        names = {f.name for f in self.fields}
        return not all(c in names for c in CARTESIAN)

    def field(self, name: str) -> E57Field | None:
        return next((f for f in self.fields if f.name == name), None)

    def local(self) -> np.ndarray:
        """(M, 3) float64 positions in the scan's own frame (spherical converted)."""
        cols = [self.field(n).values(self.records[n]).astype(np.float64)
                for n in (SPHERICAL if self.spherical else CARTESIAN)]
        if not self.spherical:
            return np.stack(cols, axis=1)
        r, az, el = cols
        return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                         r * np.sin(el)], axis=1)

    def world(self) -> np.ndarray:
        """(V, 3) float64 positions of the valid points, the pose applied."""
        return self.local()[self.valid] @ self.rotation.T + self.translation

    def grid(self) -> str:
        rows = _value(self.header, "indexBounds", "rowMaximum")
        cols = _value(self.header, "indexBounds", "columnMaximum")
        if self.field("rowIndex") is None or self.field("columnIndex") is None or rows is None:
            return ""
        return f"grid {int(rows) + 1}x{int(cols) + 1}"

    def summary(self) -> str:
        pose = "pose" if _child(self.header, "pose") else "no pose"
        grid = self.grid()
        names = " ".join(f.name for f in self.fields)
        return (f"scan {self.name!r}: {len(self.records):,} points ({int(self.valid.sum()):,} "
                f"valid), {'spherical' if self.spherical else 'cartesian'}, {pose}"
                + (f", {grid}" if grid else "") + f"; fields {names}")


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the quaternion (w, x, y, z) (normalised; a zero one: identity)."""
    norm = float(np.linalg.norm(q))
    if norm == 0.0 or not np.isfinite(norm):
        return np.eye(3)
    w, x, y, z = q / norm
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@dataclass
class E57Source:
    """Everything an E57 file held that is kept (its scans; the root's coordinate metadata).
    Answers like a :class:`PlySource` (``element('vertex')``, ``elements``, ``comments``): the
    valid points' fields, with x y z in the world frame and the scan index."""

    scans: list[E57Scan]
    coordinate_metadata: str = ""
    version: tuple[int, int] = (1, 0)
    obj_info: list[str] = field(default_factory=list)
    text: bool = False
    byte_order: str = "<"

    @property
    def format_name(self) -> str:
        return f"E57 {self.version[0]}.{self.version[1]}, {len(self.scans)} scan(s)"

    @property
    def comments(self) -> list[str]:
        return [self.format_name, *(s.summary() for s in self.scans)]

    def element(self, name: str) -> PlyElementData | None:
        return self.elements[0] if name == "vertex" else None

    @property
    def elements(self) -> list[PlyElementData]:
        names = []
        for scan in self.scans:
            names += [f.name for f in scan.fields if f.name not in names]
        columns: dict[str, list[np.ndarray]] = {n: [] for n in ("x", "y", "z", "scan", *names)}
        for k, scan in enumerate(self.scans):
            xyz = scan.world()
            for i, a in enumerate("xyz"):
                columns[a].append(xyz[:, i])
            columns["scan"].append(np.full(len(xyz), k, dtype=np.uint16))
            for n in names:
                f = scan.field(n)
                columns[n].append(np.zeros(len(xyz)) if f is None
                                  else f.values(scan.records[n][scan.valid]))
        flat = {n: np.concatenate(v) for n, v in columns.items()}
        flat = {n: (v.astype(np.float64) if v.dtype.itemsize == 8 and v.dtype.kind in "iu" else v)
                for n, v in flat.items()}
        data = np.empty(len(flat["x"]), dtype=[(n, v.dtype) for n, v in flat.items()])
        props = []
        for n, v in flat.items():
            data[n] = v
            props.append(PlyProperty(n, v.dtype.str[1:], TYPE_NAMES[v.dtype.str[1:]]))
        return [PlyElementData("vertex", props, data)]


# ---- reading ------------------------------------------------------------------------------

def _fail(path, exc: BaseException) -> FormatError:
    text = " ".join(str(exc).split())[:200] or type(exc).__name__
    return FormatError(f"{path}: cannot read E57: {text}")


def _prototype(node) -> list[E57Field]:
    lib = _libe57()
    proto = lib.StructureNode(node.prototype())
    fields = []
    for i in range(proto.childCount()):
        item = _capture(proto.get(i))
        if item is None or item[0] not in ("I", "SI", "F"):
            raise FormatError(f"point field {proto.get(i).elementName()!r} is not a number")
        if item[0] == "I":
            fields.append(E57Field(item[1], "I", item[3], item[4]))
        elif item[0] == "SI":
            fields.append(E57Field(item[1], "SI", item[3], item[4], item[5], item[6]))
        else:
            fields.append(E57Field(item[1], "F", item[4], item[5], single=item[3]))
    return fields


def _read_scan(imf, path, scan_node, index: int, declared: int) -> E57Scan:
    lib = _libe57()
    struct_node = lib.StructureNode(scan_node)
    if not struct_node.isDefined("points"):
        raise FormatError(f"{path}: E57 scan {index} has no points")
    points = lib.CompressedVectorNode(struct_node.get("points"))
    try:
        fields = _prototype(points)
    except FormatError as exc:
        raise FormatError(f"{path}: E57 scan {index}: {exc}") from None
    names = {f.name for f in fields}
    if not (all(c in names for c in CARTESIAN) or all(c in names for c in SPHERICAL)):
        raise FormatError(f"{path}: E57 scan {index} has neither cartesianX/Y/Z nor "
                          "sphericalRange/Azimuth/Elevation")
    n = int(points.childCount())
    dtype = np.dtype([(f.name, f.dtype) for f in fields])
    check_declared(path, f"E57 scan {index} ({n:,} points declared)", n * (dtype.itemsize + 48))
    records = np.empty(n, dtype=dtype)
    if n:
        columns = {f.name: np.empty(n, dtype=f.dtype) for f in fields}
        buffers = lib.VectorSourceDestBuffer()
        for f in fields:
            buffers.append(lib.SourceDestBuffer(imf, f.name, columns[f.name], n, True, False))
        reader = points.reader(buffers)
        got = reader.read()
        reader.close()
        if got != n:
            raise FormatError(f"{path}: E57 scan {index} holds {got:,} of its {n:,} points")
        for name, column in columns.items():
            records[name] = column
    header = _capture(scan_node)
    header = ("S", header[1], [c for c in header[2] if c[1] != "points"])
    state = "sphericalInvalidState" if not all(c in names for c in CARTESIAN) \
        else "cartesianInvalidState"
    valid = records[state] == 0 if state in names else np.ones(n, dtype=bool)
    scan = E57Scan(header, fields, records, valid)
    if valid.any() and not np.isfinite(scan.local()[valid]).all():
        raise FormatError(f"{path}: E57 scan {index} holds non-finite coordinates")
    return scan


def read_source(path: str | Path) -> E57Source:
    """Every scan of the E57 file at ``path`` (header checked first, through the one opener)."""
    path = Path(path)
    declared = file_points(path)
    lib = _libe57()
    try:
        imf = lib.ImageFile(str(path), "r")
    except Exception as exc:   # libE57's E57Exception and pybind's errors
        raise _fail(path, exc) from None
    try:
        root = imf.root()
        if not root.isDefined("data3D"):
            raise FormatError(f"{path}: the E57 file has no data3D section")
        data3d = lib.VectorNode(root.get("data3D"))
        scans = [_read_scan(imf, path, data3d.get(i), i,
                            declared[i] if i < len(declared) else 0)
                 for i in range(data3d.childCount())]
        meta = lib.StringNode(root.get("coordinateMetadata")).value() \
            if root.isDefined("coordinateMetadata") else ""
        version = (int(lib.IntegerNode(root.get("versionMajor")).value()),
                   int(lib.IntegerNode(root.get("versionMinor")).value())) \
            if root.isDefined("versionMajor") and root.isDefined("versionMinor") else (1, 0)
    except FormatError:
        raise
    except Exception as exc:
        raise _fail(path, exc) from None
    finally:
        imf.close()
    if not scans or not any(s.valid.any() for s in scans):
        raise FormatError(f"{path}: the E57 file holds no valid points")
    return E57Source(scans, meta, version)


def _colors(source: E57Source) -> np.ndarray | None:
    if not all(all(s.field(c) is not None for c in COLOURS) for s in source.scans):
        return None
    parts = []
    for scan in source.scans:
        rgb = []
        for c in COLOURS:
            f = scan.field(c)
            lo = _value(scan.header, "colorLimits", f"{c}Minimum", default=f.minimum)
            hi = _value(scan.header, "colorLimits", f"{c}Maximum", default=f.maximum)
            values = f.values(scan.records[c][scan.valid]).astype(np.float64)
            span = float(hi) - float(lo)
            rgb.append(np.clip(np.rint((values - float(lo)) * 255.0 / span) if span > 0
                               else values, 0, 255))
        parts.append(np.stack(rgb, axis=1))
    return np.concatenate(parts).astype(np.uint8)


def read_model(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    """Load every scan of an E57 file as one PointModel in the world frame (poses applied)."""
    source = read_source(path)
    positions = np.concatenate([s.world() for s in source.scans])
    kind = classify(has_faces=False, has_normals=False, has_radius=False, has_axes=False,
                    has_gaussians=False)
    return PointModel(positions=positions, colors=_colors(source), kind=kind, source=source,
                      path=str(path))


def ply_source_from_e57(source: E57Source) -> PlySource:
    """Every scan's fields as PLY vertex properties, x y z in the world frame and the scan
    index (for E57 -> PLY conversion)."""
    return PlySource(elements=source.elements, comments=[f"converted from {source.format_name}"])
