"""LAS/LAZ files <-> :class:`PointModel` (laspy; LAZ through the lazrs backend).

A LAS file stores points as fixed-size records (point formats 0-10) with scaled int32
coordinates ``x = X * scale + offset``. The model keeps the whole file (:class:`LasSource`):
the header (version, point format, scale, offset, every header field), VLRs and EVLRs (CRS,
extra-bytes descriptions, anything else) and the raw point records, so a save writes every
standard and extra-bytes dimension back bit for bit, in the same point order; only X, Y and Z
are re-quantised from the model's positions (with the input's scale and offset; unchanged
points keep their integers exactly). When a deformed coordinate would not fit int32, the
offset is moved by a whole number of scale steps (no precision lost), and only when the
extent itself does not fit is the scale widened, with a warning naming the file.

Models not read from LAS are written as LAS 1.4 point format 6 (7 with colours), with normals
and other numeric per-point properties as extra-bytes dimensions.

Chunked access for the streaming and Dask paths: :class:`LasChunks` (over :func:`iter_chunks`)
and :class:`LasWriter`.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FormatError, ProcessingError
from ..model import PlyElementData, PlyProperty, PlySource, PointModel, classify
from .chunks import ChunkFile
from .las_header import check_header, scale_offset_fault
from .las_keep import COPC_NOTE, RawLas, read_raw, restore, writable_evlrs, writable_vlrs
from .ply_format import TYPE_NAMES

DECODE_CHUNK = 50_000  # points per read (LAZ's default chunk): a corrupt body names this chunk
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1
NORMAL_NAMES = ("nx", "ny", "nz")


def _laspy():
    import laspy

    return laspy


@dataclass
class LasSource:
    """Everything a LAS/LAZ file held, kept for a lossless save.

    header: the ``laspy.LasHeader`` (version, point format, scales, offsets, VLRs, all fields).
    points: (N,) raw point records, the point format's structured dtype (X Y Z int32 ...).
    evlrs: extended VLRs (LAS 1.4), or None. compressed: the input was LAZ.
    raw: the file's own header, VLR and EVLR bytes (:mod:`~splatdeform.io.las_keep`), put
    back by a save.

    It also answers like a :class:`PlySource` (``element('vertex')``, ``elements``,
    ``comments``) with the decoded dimensions, so ``info`` and the ``property`` selector see
    every LAS dimension (e.g. ``{property: {name: classification, equals: 2}}``).
    """

    header: object
    points: np.ndarray
    evlrs: list | None = None
    compressed: bool = False
    obj_info: list[str] = field(default_factory=list)
    text: bool = False
    byte_order: str = "<"
    raw: RawLas | None = None

    @property
    def point_format_id(self) -> int:
        return int(self.header.point_format.id)

    @property
    def format_name(self) -> str:
        kind = " (COPC)" if self.raw is not None and self.raw.copc else \
            " (LAZ)" if self.compressed else ""
        return f"LAS {self.header.version} point format {self.point_format_id}{kind}"

    @property
    def comments(self) -> list[str]:
        h = self.header
        return [self.format_name,
                f"scale {list(map(float, h.scales))} offset {list(map(float, h.offsets))}",
                f"vlrs {len(h.vlrs)} evlrs {len(self.evlrs or [])}"]

    def element(self, name: str) -> PlyElementData | None:
        if name != "vertex":
            return None
        return decoded_element(self.header, self.points)

    @property
    def elements(self) -> list[PlyElementData]:
        return [self.element("vertex")]


def _record(header, points: np.ndarray):
    laspy = _laspy()
    return laspy.ScaleAwarePointRecord(points, header.point_format, header.scales, header.offsets)


def decoded_element(header, points: np.ndarray) -> PlyElementData:
    """The decoded dimensions as one PLY-like vertex element: x y z (float64, scaled), then
    every other dimension; multi-value extra bytes become ``name_0 ..``; bit flags uchar;
    64-bit integers double (PLY has no 64-bit integer type)."""
    record = _record(header, points)
    columns: list[tuple[str, np.ndarray]] = [(a, np.asarray(record[a], dtype=np.float64))
                                             for a in "xyz"]
    for dim in header.point_format.dimensions:
        if dim.name in ("X", "Y", "Z"):
            continue
        values = np.asarray(record[dim.name])
        if values.dtype == bool:
            values = values.astype(np.uint8)
        if values.dtype.itemsize == 8 and values.dtype.kind in "iu":
            values = values.astype(np.float64)
        if values.ndim == 2:
            columns += [(f"{dim.name}_{i}", values[:, i]) for i in range(values.shape[1])]
        else:
            columns.append((dim.name, values))
    data = np.empty(points.shape[0], dtype=[(n, v.dtype) for n, v in columns])
    props = []
    for n, v in columns:
        data[n] = v
        code = v.dtype.str[1:]
        props.append(PlyProperty(n, code, TYPE_NAMES[code]))
    return PlyElementData("vertex", props, data)


def positions_of(header, points: np.ndarray) -> np.ndarray:
    """(N, 3) float64 model coordinates X * scale + offset of raw records (N,)."""
    scales, offsets = np.asarray(header.scales), np.asarray(header.offsets)
    out = np.empty((points.shape[0], 3), dtype=np.float64)
    for i, axis in enumerate("XYZ"):
        out[:, i] = points[axis] * scales[i] + offsets[i]
    return out


def _colors(header, points: np.ndarray) -> np.ndarray | None:
    names = points.dtype.names or ()
    if not all(c in names for c in ("red", "green", "blue")):
        return None
    rgb = np.stack([points[c] for c in ("red", "green", "blue")], axis=1)
    if rgb.size and rgb.max() > 255:  # 16-bit colour (the LAS convention); else 8-bit values
        rgb = rgb >> 8
    return rgb.astype(np.uint8)


def _normals(points: np.ndarray) -> np.ndarray | None:
    names = points.dtype.names or ()
    if not all(n in names for n in NORMAL_NAMES):
        return None
    normals = np.stack([points[n].astype(np.float64) for n in NORMAL_NAMES], axis=1)
    return normals if np.any(normals) else None


def model_from_las(header, points: np.ndarray, path: str | Path, *, evlrs=None,
                   compressed: bool = False, drop_nonfinite: bool = False,
                   raw: RawLas | None = None) -> PointModel:
    """Build a PointModel from raw LAS records (N,); LAS coordinates are always finite."""
    if points.shape[0] == 0:
        raise FormatError(f"{path}: the LAS file holds no points")
    source = LasSource(header=header, points=points, evlrs=evlrs, compressed=compressed,
                       raw=raw)
    normals = _normals(points)
    kind = classify(has_faces=False, has_normals=normals is not None, has_radius=False,
                    has_axes=False, has_gaussians=False)
    return PointModel(positions=positions_of(header, points), normals=normals,
                      colors=_colors(header, points), kind=kind, source=source, path=str(path))


def _decode_failure(exc: BaseException) -> bool:
    """A failure of the decoder on a corrupt body: laspy's and lazrs's errors, numpy/struct
    complaints about short buffers, and pyo3's PanicException (a BaseException)."""
    if isinstance(exc, MemoryError):
        return False
    return isinstance(exc, Exception) or type(exc).__name__ == "PanicException"


def _read_records(path: Path, reader, start: int, stop: int, chunk: int) -> Iterator[np.ndarray]:
    """Raw records [start, stop) from an open laspy reader, ``chunk`` at a time; a corrupt or
    short body is one FormatError naming the file and the points of the chunk."""
    pos = start
    while pos < stop:
        n = min(chunk, stop - pos)
        try:
            record = reader.read_points(n)
            array = np.asarray(record.array)
        except BaseException as exc:
            if not _decode_failure(exc):
                raise
            msg = " ".join(str(exc).split())[:200] or type(exc).__name__
            raise FormatError(f"{path}: corrupt LAS/LAZ point data in the chunk of points "
                              f"{pos}..{pos + n - 1}: {type(exc).__name__}: {msg}") from None
        if len(array) == 0:
            raise FormatError(f"{path}: truncated LAS/LAZ point data at point {pos} (the header "
                              f"declares {stop})")
        pos += len(array)
        yield array


#: a streamed LAZ read decodes on lazrs's parallel backend when the file's chunks are at most
#: this many bytes of records (what it holds beyond the sequential one: one chunk's rest)
PARALLEL_CHUNK_BYTES = 16 * 2**20


def _parallel_ok(path: Path) -> bool:
    """A streamed read may decode on several cores: there are cores for it and the file's LAZ
    chunks are of a known, small size (5M points, 2 cores: 3.5 -> 2.3 s, +5 MB peak)."""
    import os

    if (os.cpu_count() or 1) < 2:
        return False
    layout = check_header(path)
    return 0 < layout.laz_chunk_points * layout.record_length <= PARALLEL_CHUNK_BYTES


def _open(path: Path, sequential: bool = False):
    """laspy reader of a LAS/LAZ file whose header :func:`check_header` accepted.
    ``sequential``: LAZ through lazrs's one-thread decompressor, which holds one compressed
    chunk at a time (the default, parallel one decompresses whole LAZ chunks into a buffer
    beside the points asked for: with a file written as one big chunk that is the whole
    file's records, see :func:`splatdeform.memory.laz_reader_bytes`), or its parallel one
    where :func:`_parallel_ok` (chunks of a known small size: one chunk's rest is held)."""
    laspy = _laspy()
    try:
        if sequential:
            par = laspy.LazBackend.LazrsParallel
            backend = par if _parallel_ok(path) and par.is_available() else \
                laspy.LazBackend.Lazrs
            return laspy.open(path, laz_backend=backend)
        return laspy.open(path)
    except BaseException as exc:
        if not _decode_failure(exc):
            raise
        raise FormatError(f"{path}: cannot read LAS/LAZ: {type(exc).__name__}: "
                          f"{' '.join(str(exc).split())[:200]}") from None


def read_model(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    """Load a .las/.laz file as a PointModel (raises FormatError naming the file; the header
    is checked against the file size first, the points are decoded chunk by chunk)."""
    path = Path(path)
    layout = check_header(path)
    raw = read_raw(path)
    with _open(path) as reader:
        header = reader.header
        evlrs = getattr(reader, "evlrs", None)
        chunks = _read_records(path, reader, 0, layout.point_count, DECODE_CHUNK)
        if layout.compressed:   # the count is only bounded loosely: grow with what decodes
            parts = list(chunks)
            points = parts[0] if len(parts) == 1 else np.concatenate(parts) if parts else None
            del parts
        else:                   # the count was checked against the file: fill one array
            points = None
            at = 0
            for part in chunks:
                if points is None:
                    points = np.empty(layout.point_count, dtype=part.dtype)
                points[at:at + len(part)] = part
                at += len(part)
    if points is None or len(points) == 0:
        raise FormatError(f"{path}: the LAS file holds no points")
    compressed = layout.compressed or path.suffix.lower() == ".laz"
    return model_from_las(header, points, path, evlrs=evlrs, compressed=compressed,
                          drop_nonfinite=drop_nonfinite, raw=raw)


# ---- writing ---------------------------------------------------------------------------------

def fit_offsets(header, lo: np.ndarray, hi: np.ndarray, path: str | Path) -> tuple[
        np.ndarray, np.ndarray, np.ndarray]:
    """Scales, offsets and integer shift (3,) int64 that make coordinates in [lo, hi] fit
    int32. The input's scale and offset are kept when they fit; else the offset moves by a
    whole number of scale steps (shift, so unchanged points keep their exact coordinates);
    only an extent beyond 2^32 steps widens the scale (with a warning)."""
    scales = np.asarray(header.scales, dtype=np.float64).copy()
    offsets = np.asarray(header.offsets, dtype=np.float64).copy()
    shift = np.zeros(3, dtype=np.int64)
    for i, axis in enumerate("xyz"):
        ilo = np.floor((lo[i] - offsets[i]) / scales[i])
        ihi = np.ceil((hi[i] - offsets[i]) / scales[i])
        if ilo >= INT32_MIN and ihi <= INT32_MAX:
            continue
        if ihi - ilo <= INT32_MAX:  # move the offset by whole steps
            shift[i] = int((ilo + ihi) // 2)
            offsets[i] = offsets[i] + shift[i] * scales[i]
            warnings.warn(f"{path}: deformed {axis} coordinates overflow the LAS int32 range "
                          f"with offset {header.offsets[i]}; moved the {axis} offset to "
                          f"{offsets[i]} (scale {scales[i]} kept)", stacklevel=3)
            continue
        old = scales[i]
        while (hi[i] - lo[i]) / scales[i] > INT32_MAX - 2:
            scales[i] *= 10.0
        offsets[i] = (lo[i] + hi[i]) / 2.0
        shift[i] = 0
        warnings.warn(f"{path}: deformed {axis} extent {hi[i] - lo[i]:.6g} does not fit int32 "
                      f"with scale {old}; widened the {axis} scale to {scales[i]} (coarser "
                      "precision)", stacklevel=3)
    return scales, offsets, shift


def check_writable(scales: np.ndarray, offsets: np.ndarray, lo: np.ndarray,
                   hi: np.ndarray) -> None:
    """Refuse (one line; the writer names the output) a scale and offset the LAS reader would
    refuse (:func:`~splatdeform.io.las_header.scale_offset_fault`, the one rule): coordinates
    in [lo, hi] (3,) too far from the origin for a LAS file."""
    for i, axis in enumerate("xyz"):
        fault = scale_offset_fault(axis, float(scales[i]), float(offsets[i]))
        if fault:
            top = max(abs(float(lo[i])), abs(float(hi[i])))
            raise FormatError(f"{axis} coordinates reach {top:g}: a LAS file cannot hold them "
                              f"({fault}, which LAS readers refuse); write .ply or .pcd")


def quantize(positions: np.ndarray, original: np.ndarray | None, original_xyz: np.ndarray | None,
             scales: np.ndarray, offsets: np.ndarray, shift: np.ndarray,
             keep_ints: bool) -> np.ndarray:
    """(N, 3) int32 X Y Z of positions (N, 3). Points whose position equals ``original`` keep
    their input integers (minus ``shift``) exactly, when ``keep_ints`` (same scale)."""
    ints = np.rint((positions - offsets) / scales)
    if keep_ints and original is not None:
        same = positions == original
        ints = np.where(same, original_xyz.astype(np.float64) - shift, ints)
    if ints.size and (ints.min() < INT32_MIN or ints.max() > INT32_MAX):
        raise ProcessingError("LAS coordinates overflow int32 after quantisation")
    return ints.astype(np.int32)


def _original_xyz(points: np.ndarray) -> np.ndarray:
    return np.stack([points[a] for a in "XYZ"], axis=1)


def requantized(header, points: np.ndarray, model: PointModel, scales: np.ndarray,
                offsets: np.ndarray, shift: np.ndarray, keep_ints: bool) -> np.ndarray:
    """A copy of the raw records ``points`` (N,) read with ``header``, X Y Z re-quantised from
    ``model.positions`` (N, 3) (:func:`quantize`) and its normals written into nx ny nz when
    the records have them."""
    ints = quantize(model.positions, positions_of(header, points), _original_xyz(points),
                    scales, offsets, shift, keep_ints)
    out = points.copy()
    for i, axis in enumerate("XYZ"):
        out[axis] = ints[:, i]
    if model.normals is not None and all(n in (out.dtype.names or ()) for n in NORMAL_NAMES):
        for i, n in enumerate(NORMAL_NAMES):
            out[n] = model.normals[:, i].astype(out.dtype[n])
    return out


def las_records_for(model: PointModel, path: str | Path):
    """(header, raw records (N,)) to write for ``model``: its LAS source with re-quantised
    coordinates, or a new LAS 1.4 file for models from other formats."""
    laspy = _laspy()
    src = model.source if isinstance(model.source, LasSource) else None
    if src is None:
        return _new_las(model)
    if src.points.shape[0] != model.n_points:
        raise FormatError(f"model has {model.n_points} points but its LAS source "
                          f"{src.points.shape[0]}; cannot save it verbatim")
    header = src.header
    lo, hi = model.bbox()
    with warnings.catch_warnings(record=True) as said:  # said only once the fit is writable
        warnings.simplefilter("always")
        scales, offsets, shift = fit_offsets(header, lo, hi, path)
    check_writable(scales, offsets, lo, hi)
    for w in said:
        warnings.warn(str(w.message), w.category, stacklevel=2)
    same_scale = bool(np.all(scales == np.asarray(header.scales)))
    points = requantized(header, src.points, model, scales, offsets, shift, same_scale)
    if np.any(shift) or not same_scale:
        header = _copy_header(header)
        header.offsets = offsets
        header.scales = scales
    del laspy
    return header, points


def _copy_header(header):
    import copy

    return copy.deepcopy(header)


def _new_las(model: PointModel):
    """A LAS 1.4 header and records for a model from another format."""
    laspy = _laspy()
    fmt = 7 if model.colors is not None else 6
    header = laspy.LasHeader(version="1.4", point_format=fmt)
    extra: list[tuple[str, np.ndarray]] = []
    if model.normals is not None:
        extra += [(n, model.normals[:, i].astype(np.float32)) for i, n in enumerate(NORMAL_NAMES)]
    vertex = model.source.element("vertex") if isinstance(model.source, PlySource) else None
    if vertex is not None:
        skip = {"x", "y", "z", "red", "green", "blue", *NORMAL_NAMES}
        for p in vertex.properties:
            if not p.is_list and p.name not in skip:
                extra.append((p.name, np.asarray(vertex.data[p.name])))
    taken = {d.name for d in header.point_format.dimensions}
    extra = [(n, v) for n, v in extra if n not in taken]
    if extra:
        header.add_extra_dims([laspy.ExtraBytesParams(name=n, type=v.dtype) for n, v in extra])
    lo, hi = model.bbox()
    extent = float(np.max(hi - lo)) or 1.0
    step = 10.0 ** np.ceil(np.log10(extent / 2**30))  # ~1e-9 of the extent, a power of ten
    header.scales = np.full(3, max(step, 1e-9))
    header.offsets = np.round((lo + hi) / 2.0 / step) * step
    check_writable(header.scales, header.offsets, lo, hi)
    record = laspy.ScaleAwarePointRecord.zeros(model.n_points, header=header)
    points = np.asarray(record.array)
    ints = np.rint((model.positions - header.offsets) / header.scales).astype(np.int32)
    for i, axis in enumerate("XYZ"):
        points[axis] = ints[:, i]
    if model.colors is not None:
        for i, c in enumerate(("red", "green", "blue")):
            points[c] = model.colors[:, i].astype(np.uint16) * 257
    for n, v in extra:
        points[n] = v
    return header, points


def _vlr_bytes(header) -> list[tuple[str, int, bytes]]:
    return [(v.user_id, v.record_id, bytes(v.record_data_bytes())) for v in header.vlrs]


def restore_vlrs(out: Path, original) -> None:
    """Put the input's VLR payloads back verbatim where laspy regenerated them on write (it
    rewrites the extra-bytes descriptions' statistics fields): same-length payloads only, in
    the header area of ``out``."""
    laspy = _laspy()
    want = _vlr_bytes(original)
    with laspy.open(out) as reader:
        got = _vlr_bytes(reader.header)
        head_size = int(reader.header.offset_to_point_data)
    patches = [(g[2], w[2]) for w, g in zip(want, got, strict=False)
               if w[:2] == g[:2] and w[2] != g[2] and len(w[2]) == len(g[2])]
    if not patches:
        return
    with open(out, "r+b") as f:
        head = bytearray(f.read(head_size))
        for generated, verbatim in patches:
            at = head.find(generated)
            if at >= 0:
                head[at:at + len(verbatim)] = verbatim
        f.seek(0)
        f.write(head)


def _kept_header(header, evlrs, raw: RawLas | None):
    """A copy of ``header`` to hand laspy, and the EVLRs to write: with the input's bytes
    (``raw``), its VLRs and EVLRs as opaque records of their own length, so that
    :func:`~splatdeform.io.las_keep.restore` can put every byte back in place."""
    header = _copy_header(header)
    if raw is not None:
        header.vlrs = writable_vlrs(raw)
        with contextlib.suppress(IndexError, ValueError):   # laspy's setter adds its own
            header.vlrs.extract("ExtraBytesVlr")            # copy of the extra-bytes VLR
        kept = writable_evlrs(raw)
        if kept is not None:
            from laspy.vlrs.vlrlist import VLRList

            evlrs = VLRList(kept)
    return header, evlrs


def _finish(out: Path, original, raw: RawLas | None) -> None:
    if raw is not None:
        restore(out, raw)
    else:
        restore_vlrs(out, original)


def _write_records(header, points: np.ndarray, out: Path, evlrs=None,
                   raw: RawLas | None = None) -> None:
    laspy = _laspy()
    do_compress = out.suffix.lower() == ".laz"
    original = header
    header, evlrs = _kept_header(header, evlrs, raw)
    if raw is not None and raw.copc:
        warnings.warn(f"{out}: {COPC_NOTE}", stacklevel=3)
    with laspy.open(out, mode="w", header=header, do_compress=do_compress) as writer:
        writer.write_points(laspy.PackedPointRecord(points, header.point_format))
        if evlrs:
            writer.write_evlrs(evlrs)
    _finish(out, original, raw)


def write_model(model: PointModel, out: str | Path) -> None:
    """Write ``model`` to ``out`` (.las or .laz by the suffix; call through an atomic path)."""
    out = Path(out)
    header, points = las_records_for(model, out)
    source = model.source if isinstance(model.source, LasSource) else None
    _write_records(header, points, out, source.evlrs if source else None,
                   source.raw if source else None)


def ply_source_from_las(source: LasSource) -> PlySource:
    """A PLY source holding every decoded LAS dimension (for LAS -> PLY conversion)."""
    return PlySource(elements=[source.element("vertex")],
                     comments=[f"converted from {source.format_name}"])


# ---- chunked access (streaming, Dask) ----------------------------------------------------

def read_header(path: str | Path):
    """(header, compressed, evlrs) of a LAS/LAZ file without reading its points."""
    path = Path(path)
    layout = check_header(path)
    with _open(path) as reader:
        evlrs = getattr(reader, "evlrs", None)
        return reader.header, layout.compressed, evlrs


def _seek(path: Path, reader, start: int) -> None:
    try:
        reader.seek(start)
    except BaseException as exc:
        if not _decode_failure(exc):
            raise
        raise FormatError(f"{path}: corrupt LAS/LAZ point data: cannot seek to point "
                          f"{start}: {type(exc).__name__}") from None


def iter_chunks(path: str | Path, chunk: int, start: int = 0,
                stop: int | None = None) -> Iterator[np.ndarray]:
    """Raw point records of points [start, stop) in chunks of at most ``chunk`` rows (LAZ
    through the sequential decompressor: memory bounded by one compressed chunk)."""
    path = Path(path)
    layout = check_header(path)
    stop = layout.point_count if stop is None else min(stop, layout.point_count)
    with _open(path, sequential=True) as reader:
        if start:
            _seek(path, reader, start)
        yield from _read_records(path, reader, start, stop, chunk)


class LasWriter:
    """Append raw records chunk by chunk to ``out`` (compressed for .laz); the header is the
    input's (point count and bounds are updated by laspy at close; with the input's bytes
    ``raw``, its header fields, VLRs and EVLRs are put back as
    :mod:`~splatdeform.io.las_keep` says)."""

    def __init__(self, header, out: str | Path, evlrs=None, raw: RawLas | None = None) -> None:
        laspy = _laspy()
        self._laspy = laspy
        self._original = header
        self._raw = raw
        self.header, evlrs = _kept_header(header, evlrs, raw)
        self.out = Path(out)
        if raw is not None and raw.copc:
            warnings.warn(f"{self.out}: {COPC_NOTE}", stacklevel=2)
        self._evlrs = evlrs
        self._writer = laspy.open(self.out, mode="w", header=self.header,
                                  do_compress=self.out.suffix.lower() == ".laz")

    def write(self, points: np.ndarray) -> None:
        self._writer.write_points(self._laspy.PackedPointRecord(points,
                                                                self.header.point_format))

    def close(self) -> None:
        if self._evlrs:
            self._writer.write_evlrs(self._evlrs)
        self._writer.close()
        _finish(self.out, self._original, self._raw)


class LasChunks(ChunkFile):
    """LAS/LAZ (every point format) in chunks; deformed chunks keep every record field, with
    X Y Z re-quantised on the input's scale and offset."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.header, self.compressed, self.evlrs = read_header(self.path)
        self.raw = read_raw(self.path)
        self.n_points = int(self.header.point_count)
        self.record_bytes = int(self.header.point_format.size)
        self.scales = np.asarray(self.header.scales, dtype=np.float64)
        self.offsets = np.asarray(self.header.offsets, dtype=np.float64)
        self._reader = None   # kept open between rows() calls that follow each other
        self._at = -1

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_reader"], state["_at"] = None, -1   # an open reader does not travel
        return state

    def rows(self, start: int, stop: int) -> np.ndarray:
        """Raw records [start, stop). Reads that follow each other (every pass) go on with one
        open reader: a LAZ chunk is decompressed once, not again from its start for every
        streamed chunk (a LAZ written as one chunk would otherwise cost quadratic time)."""
        stop = min(stop, self.n_points)
        if self._reader is None or start != self._at:
            self.close()
            check_header(self.path)
            self._reader = _open(self.path, sequential=True)
            if start:
                _seek(self.path, self._reader, start)
        try:
            parts = list(_read_records(self.path, self._reader, start, stop, stop - start))
        except BaseException:
            self.close()
            raise
        self._at = stop
        if stop >= self.n_points:
            self.close()
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def close(self) -> None:
        """Close the reader kept between reads (reopened when needed)."""
        if self._reader is not None:
            reader, self._reader, self._at = self._reader, None, -1
            reader.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    def positions(self, start: int, stop: int) -> np.ndarray:
        return positions_of(self.header, self.rows(start, stop))

    def model_of(self, rows: np.ndarray) -> PointModel:
        return model_from_las(self.header, rows, self.path, compressed=self.compressed,
                              raw=self.raw)

    def encode(self, model: PointModel) -> tuple[np.ndarray, None]:
        """Raises ProcessingError when a coordinate leaves int32 (the offset stays)."""
        return requantized(self.header, model.source.points, model, self.scales, self.offsets,
                           np.zeros(3, dtype=np.int64), True), None

    def writer(self, out: Path, props: list | None = None) -> LasWriter:
        return LasWriter(self.header, out, self.evlrs, self.raw)
