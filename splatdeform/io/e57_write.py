"""Write a :class:`PointModel` as E57 through pye57's libE57Format binding (what is kept and
what changes: :mod:`splatdeform.io.e57`)."""

from __future__ import annotations

import uuid
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..model import PointModel
from .e57 import CARTESIAN, COLOURS, SPHERICAL, E57Field, E57Scan, E57Source, _build, _libe57

WRITE_CHUNK = 1 << 20   # points per libE57 write


def _root(imf, meta: str) -> None:
    """The root nodes every E57 file has (as pye57's default header writes them)."""
    lib = _libe57()
    imf.extensionsAdd("", lib.E57_V1_0_URI)
    root = imf.root()
    root.set("formatName", lib.StringNode(imf, "ASTM E57 3D Imaging Data File"))
    root.set("guid", lib.StringNode(imf, f"{{{uuid.uuid4()}}}"))
    root.set("versionMajor", lib.IntegerNode(imf, lib.E57_FORMAT_MAJOR))
    root.set("versionMinor", lib.IntegerNode(imf, lib.E57_FORMAT_MINOR))
    root.set("e57LibraryVersion", lib.StringNode(imf, lib.E57_LIBRARY_ID))
    root.set("coordinateMetadata", lib.StringNode(imf, meta))
    created = lib.StructureNode(imf)
    created.set("dateTimeValue", lib.FloatNode(imf, 0.0))
    created.set("isAtomicClockReferenced", lib.IntegerNode(imf, 0))
    root.set("creationDateTime", created)
    root.set("data3D", lib.VectorNode(imf, True))
    root.set("images2D", lib.VectorNode(imf, True))


def _raw(f: E57Field, values: np.ndarray) -> np.ndarray:
    """Values in the field's stored form (scaled integers as raw integers)."""
    if f.kind == "F":
        return values.astype(f.dtype)
    raw = np.rint((values - f.offset) / f.scale) if f.kind == "SI" else np.rint(values)
    return raw


def _widened(f: E57Field, raw: np.ndarray) -> E57Field:
    """``f`` with its minimum and maximum covering ``raw`` (its stored values)."""
    if not len(raw):
        return f
    lo, hi = min(f.minimum, raw.min()), max(f.maximum, raw.max())
    if f.kind == "F":
        return replace(f, minimum=float(lo), maximum=float(hi))
    return replace(f, minimum=int(lo), maximum=int(hi))


def _put(scan: E57Scan, moved: np.ndarray, local: np.ndarray) -> E57Scan:
    """``scan`` with the positions of its valid points ``local`` (V, 3) in its own frame
    written where ``moved`` (V,) (the others keep their raw values)."""
    records = scan.records.copy()
    fields = list(scan.fields)
    rows = np.flatnonzero(scan.valid)[moved]
    if scan.spherical:
        x, y, z = local[moved].T
        r = np.sqrt(x * x + y * y + z * z)
        columns = (r, np.arctan2(y, x), np.arcsin(np.divide(z, r, out=np.zeros_like(z),
                                                             where=r > 0)))
        names = SPHERICAL
    else:
        columns, names = local[moved].T, CARTESIAN
    for name, values in zip(names, columns, strict=True):
        k = next(i for i, f in enumerate(fields) if f.name == name)
        raw = _raw(fields[k], values)
        fields[k] = _widened(fields[k], raw)
        if records.dtype[name].kind in "iu":
            info = np.iinfo(records.dtype[name])
            if len(raw) and (raw.min() < info.min or raw.max() > info.max):
                wide = records.dtype.descr
                wide = [(n, "<i8" if n == name else t) for n, t in wide]
                records = records.astype(wide)
        records[name][rows] = raw
    return replace(scan, records=records, fields=fields)


def _bounds(scan: E57Scan) -> tuple:
    """The scan header with ``cartesianBounds`` recomputed from its valid points (its frame)."""
    header = scan.header
    if not scan.valid.any():
        return header
    local = scan.local()[scan.valid]
    lo, hi = local.min(axis=0), local.max(axis=0)
    box = ("S", "cartesianBounds", [("F", f"{a}{m}", float(v), False, -np.finfo(float).max,
                                      np.finfo(float).max)
                                     for a, l0, h0 in zip("xyz", lo, hi, strict=True)
                                     for m, v in (("Minimum", l0), ("Maximum", h0))])
    children = [c for c in header[2] if c[1] != "cartesianBounds"]
    if any(c[1] == "cartesianBounds" for c in header[2]) or not scan.spherical:
        children.append(box)
    return ("S", header[1], children)


def scans_for(model: PointModel) -> list[E57Scan]:
    """The scans to write for a model read from E57: each scan's valid points set from the
    model's positions (world frame) turned back into the scan's frame."""
    source: E57Source = model.source
    counts = [int(s.valid.sum()) for s in source.scans]
    if sum(counts) != model.n_points:
        raise FormatError(f"model has {model.n_points} points but its E57 scans "
                          f"{sum(counts)}; cannot save them scan by scan")
    out, at = [], 0
    for scan, n in zip(source.scans, counts, strict=True):
        world = model.positions[at:at + n]
        at += n
        moved = np.any(world != scan.world(), axis=1)
        if moved.any():
            local = (world - scan.translation) @ scan.rotation
            if not np.isfinite(local).all():
                raise FormatError("deformed E57 coordinates are not finite")
            scan = _put(scan, moved, local)
        out.append(scan)
    return out


def _new_scan(model: PointModel) -> E57Scan:
    """One scan (double precision cartesian, colour, no pose) for a model from another format."""
    n = model.n_points
    lo, hi = model.positions.min(axis=0), model.positions.max(axis=0)
    fields = [E57Field(c, "F", float(lo[i]), float(hi[i])) for i, c in enumerate(CARTESIAN)]
    columns = [model.positions[:, i] for i in range(3)]
    if model.colors is not None:
        fields += [E57Field(c, "I", 0, 255) for c in COLOURS]
        columns += [model.colors[:, i] for i in range(3)]
    records = np.empty(n, dtype=[(f.name, f.dtype) for f in fields])
    for f, c in zip(fields, columns, strict=True):
        records[f.name] = c
    header = ("S", "", [("T", "guid", f"{{{uuid.uuid4()}}}"), ("T", "name", "splatdeform"),
                        ("T", "description",
                         f"written by splatdeform from {model.path or '?'}")])
    if model.colors is not None:
        header[2].append(("S", "colorLimits", [
            ("I", f"{c}{m}", v, 0, 255) for c in COLOURS for m, v in (("Minimum", 0),
                                                                     ("Maximum", 255))]))
    return E57Scan(header, fields, records, np.ones(n, dtype=bool))


def _prototype_node(imf, fields: list[E57Field]):
    lib = _libe57()
    proto = lib.StructureNode(imf)
    for f in fields:
        if f.kind == "I":
            node = lib.IntegerNode(imf, int(f.minimum), int(f.minimum), int(f.maximum))
        elif f.kind == "SI":
            node = lib.ScaledIntegerNode(imf, int(f.minimum), int(f.minimum), int(f.maximum),
                                         f.scale, f.offset)
        else:
            precision = lib.FloatPrecision.E57_SINGLE if f.single \
                else lib.FloatPrecision.E57_DOUBLE
            node = lib.FloatNode(imf, float(f.minimum), precision, float(f.minimum),
                                 float(f.maximum))
        proto.set(f.name, node)
    return proto


def _write_scan(imf, data3d, scan: E57Scan) -> None:
    lib = _libe57()
    node = _build(imf, _bounds(scan))
    points = lib.CompressedVectorNode(imf, _prototype_node(imf, scan.fields),
                                      lib.VectorNode(imf, True))
    node.set("points", points)
    data3d.append(node)
    n = len(scan.records)
    chunk = max(1, min(n, WRITE_CHUNK))
    arrays = {f.name: np.empty(chunk, dtype=f.dtype) for f in scan.fields}   # (see E57Field)
    buffers = lib.VectorSourceDestBuffer()
    for f in scan.fields:
        buffers.append(lib.SourceDestBuffer(imf, f.name, arrays[f.name], chunk, True, False))
    writer = points.writer(buffers)
    for start in range(0, n, chunk):
        count = min(chunk, n - start)
        for name, array in arrays.items():
            array[:count] = scan.records[name][start:start + count]
        writer.write(count)
    writer.close()


def write_model(model: PointModel, out: str | Path) -> None:
    """Write ``model`` as E57 to ``out`` (call through an atomic path): an E57-read model's
    scans each as a scan, else one scan."""
    lib = _libe57()
    source = model.source if isinstance(model.source, E57Source) else None
    scans = scans_for(model) if source is not None else [_new_scan(model)]
    imf = lib.ImageFile(str(out), "w")
    try:
        _root(imf, source.coordinate_metadata if source else "")
        data3d = lib.VectorNode(imf.root().get("data3D"))
        for scan in scans:
            _write_scan(imf, data3d, scan)
        imf.close()
    except BaseException as exc:
        imf.cancel()
        if isinstance(exc, FormatError):
            raise
        if isinstance(exc, Exception):
            raise FormatError(f"cannot write E57: {' '.join(str(exc).split())[:200]}") \
                from None
        raise
