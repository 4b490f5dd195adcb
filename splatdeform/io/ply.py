"""PLY files <-> :class:`PointModel`: recognise the kind, expose the geometry, save losslessly.

Recognised vertex properties (everything else is kept verbatim and written back):
  x y z (required) · nx ny nz · red green blue · radius | surfel_radius ·
  ux uy uz vx vy vz (surfel tangent axes) · 3DGS: scale_0..2 rot_0..3 opacity f_dc_* f_rest_*.
Faces come from a ``face`` element (``vertex_indices`` or ``vertex_index``; polygons are fan
triangulated) or from a ``tristrips`` element (strips separated by -1).
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError, ProcessingError
from ..model import (
    MAX_COORDINATE,
    Gaussians,
    PlyElementData,
    PlyProperty,
    PlySource,
    PointModel,
    classify,
)
from . import playcanvas
from .checks import check_fits, infinite_opacity_ok
from .chunks import ChunkFile
from .ply_format import (
    MAX_HEADER_BYTES,
    _write_binary_element,
    header_text,
    parse_header,
    read_ply,
    write_ply,
)
from .splats import finite_opacity

AXIS_NAMES = ("ux", "uy", "uz", "vx", "vy", "vz")
RADIUS_NAMES = ("radius", "surfel_radius")


def _columns(data: np.ndarray, names: list[str] | tuple[str, ...],
             dtype: type = np.float64, *, copy: bool = True) -> np.ndarray | None:
    """(N, len(names)) ``dtype`` copy of those fields (None when one is missing); fields of one
    type are taken as a strided view first (no per-column float64 round trip), and returned as
    that view with ``copy=False`` when they already are ``dtype``."""
    if not all(n in (data.dtype.names or ()) for n in names):
        return None
    if len({data.dtype[n] for n in names}) == 1:
        # numpy.lib.recfunctions imports numpy.ma (~7 ms): only when a load needs it (a
        # convert of like PLYs copies the records as read without it)
        from numpy.lib.recfunctions import structured_to_unstructured

        return structured_to_unstructured(data[list(names)]).astype(dtype, copy=copy)
    return np.stack([data[n].astype(dtype) for n in names], axis=1)


def _shared(data: np.ndarray, names: list[str]) -> np.ndarray | None:
    """(N, len(names)) float32, read-only: a view of the source rows when they hold those fields
    as float32 at even spacing (a 3DGS PLY, every decoded splat table), else a copy (None when
    one is missing). The source stays as read: an edit works on ``model.copy()`` (as
    ``deform.apply`` does), never in place, so a writer can still tell the untouched splats."""
    columns = _columns(data, names, np.float32, copy=False)
    if columns is not None:
        columns.flags.writeable = False
    return columns


def _triangles_from_faces(column: np.ndarray) -> np.ndarray:
    if len(column) == 0:
        return np.empty((0, 3), dtype=np.int64)
    lengths = np.fromiter((len(f) for f in column), dtype=np.int64, count=len(column))
    # one concatenation of the rows as they are (np.stack would make a new view per row, and
    # a per-row int64 conversion a new array per row: hundreds of MB for millions of faces)
    flat = np.concatenate(column.tolist()).astype(np.int64) if lengths.sum() \
        else np.empty(0, dtype=np.int64)
    if (lengths == 3).all():
        return flat.reshape(-1, 3)
    # fan triangulation of every polygon at once: face f gives (f0, fi, fi+1), i = 1..len-2
    # (temporaries one at a time: a few (T,) int64 arrays, not a dozen)
    first = np.cumsum(lengths) - lengths
    fans = np.maximum(lengths - 2, 0)
    start = np.repeat(first, fans)              # each triangle's polygon's first index
    step = np.arange(int(fans.sum()), dtype=np.int64)
    step -= np.repeat(np.cumsum(fans) - fans, fans)
    tris = np.empty((len(start), 3), dtype=np.int64)
    tris[:, 0] = flat[start]
    start += step
    del step
    start += 1
    tris[:, 1] = flat[start]
    start += 1
    tris[:, 2] = flat[start]
    return tris


STRIP_BLOCK = 1 << 20  # strip positions converted at a time (bounded temporaries)


def _strip_block(s: np.ndarray, k: int, e: int, carry: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Candidate triangles at strip positions [k, e) of the strip list ``s`` (-1 separates
    strips): (T, 3) int64 triangles and (T,) bool keep (no separator, not degenerate), and the
    start of the strip that is open at ``e``. ``carry``: the start of the strip open at ``k``."""
    a, b, c = s[k:e], s[k + 1:e + 1], s[k + 2:e + 2]
    pos = np.arange(k, e, dtype=np.int64)
    starts = np.where(a < 0, pos + 1, carry)
    np.maximum.accumulate(starts, out=starts)
    odd = ((pos - starts) & 1).astype(bool)   # every other triangle of a strip is flipped
    t = np.stack([a, np.where(odd, c, b), np.where(odd, b, c)], axis=1).astype(np.int64)
    keep = (t >= 0).all(axis=1) & (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) \
        & (t[:, 0] != t[:, 2])
    return t, keep, int(starts[-1]) if len(starts) else carry


def _triangles_from_strips(column: np.ndarray) -> np.ndarray:
    """Triangles (T, 3) int64 of every strip list in ``column``, vectorised in blocks of
    positions (a list of millions of short strips is no Python loop; temporaries stay a few
    block sizes; the result is allocated once, after a counting pass)."""
    lists = [np.asarray(v) for v in column]
    blocks = [(i, k, min(k + STRIP_BLOCK, len(s) - 2))
              for i, s in enumerate(lists) for k in range(0, max(len(s) - 2, 0), STRIP_BLOCK)]
    counts, carries, carry, last = [], [], 0, -1
    for i, k, e in blocks:   # pass 1: how many triangles each block keeps
        carry = 0 if i != last else carry
        carries.append(carry)
        _, keep, carry = _strip_block(lists[i], k, e, carry)
        counts.append(int(keep.sum()))
        last = i
    out = np.empty((sum(counts), 3), dtype=np.int64)
    at = 0
    for (i, k, e), carry, n in zip(blocks, carries, counts, strict=True):  # pass 2: fill
        t, keep, _ = _strip_block(lists[i], k, e, carry)
        out[at:at + n] = t[keep]
        at += n
    return out


SPLAT_PREFIXES = ("scale_", "rot_", "f_dc_", "f_rest_")


def _nonfinite_splat_rows(data: np.ndarray) -> np.ndarray | None:
    """(N,) bool: rows whose 3DGS attributes (log-scales, rotation, opacity, SH) are NaN/Inf, or
    None when the element holds no Gaussians. They follow --drop-nonfinite like positions."""
    names = [n for n in data.dtype.names or ()
             if (n.startswith(SPLAT_PREFIXES) or n == "opacity") and data.dtype[n].kind == "f"]
    if not any(n.startswith("scale_") for n in names):
        return None
    run = _float_run(data, names)
    if run is not None:  # one pass: a float64 row sum is finite iff every term is
        with np.errstate(invalid="ignore", over="ignore"):
            return infinite_opacity_ok(data, ~np.isfinite(run.sum(axis=1, dtype=np.float64)),
                                       names)
    bad = np.zeros(data.shape[0], dtype=bool)
    for n in names:
        bad |= ~np.isfinite(data[n])
    return infinite_opacity_ok(data, bad, names)  # an opacity of +-inf is alpha 1 / 0


def _float_run(data: np.ndarray, names: list[str]) -> np.ndarray | None:
    """(N, len(names)) float32 strided view of ``names`` when they are consecutive float32
    fields of a packed record (the 3DGS layout); None otherwise."""
    dtype = data.dtype
    if not names or any(dtype[n] != np.dtype("<f4") for n in names) or \
            not data.flags.c_contiguous or dtype.itemsize % 4:
        return None
    offsets = [dtype.fields[n][1] for n in names]
    if offsets != list(range(offsets[0], offsets[0] + 4 * len(names), 4)) or \
            any(dtype.fields[n][0].itemsize != 4 or dtype.fields[n][1] % 4 for n in dtype.names):
        return None
    table = data.view(np.uint8).reshape(len(data), dtype.itemsize)
    start = offsets[0]
    return table[:, start:start + 4 * len(names)].view("<f4")


def _require_list(path: str | Path, element: str, prop) -> None:
    if not prop.is_list:
        raise FormatError(f"{path}: element '{element}' property '{prop.name}' is a scalar "
                          f"({prop.type_name}); "
                          "expected a list (property list uchar int vertex_indices)")


def nonfinite_rows(data: np.ndarray, positions: np.ndarray | None = None
                   ) -> tuple[np.ndarray, str]:
    """((N,) bool: vertex records a ``drop_nonfinite`` load drops, what is wrong in them) of
    vertex records ``data`` with x, y, z (``positions``: their (N, 3) columns, when at hand):
    a NaN/Inf coordinate or Gaussian attribute."""
    if positions is None:
        positions = _columns(data, ("x", "y", "z"))
    bad = (np.zeros(positions.shape[0], bool) if np.isfinite(positions).all()
           else ~np.isfinite(positions).all(axis=1))
    what = "coordinates"
    splat = _nonfinite_splat_rows(data)
    if splat is not None and splat.any() and not bad.any():
        what = "Gaussian attributes (scale_*, rot_*, opacity, f_dc_*, f_rest_*)"
    if splat is not None:
        bad |= splat
    return bad, what


def model_from_source(source: PlySource, path: str | Path, *,
                      drop_nonfinite: bool = False) -> PointModel:
    """Build a PointModel from a verbatim PLY source (validates coordinates and indices)."""
    vertex = source.element("vertex")
    if vertex is None:
        raise FormatError(f"{path}: no 'vertex' element")
    data = vertex.data
    positions = _columns(data, ("x", "y", "z"))
    if positions is None:
        if playcanvas.is_compressed(source):  # decoded to plain 3DGS properties
            return model_from_source(playcanvas.decompress(source, path), path,
                                     drop_nonfinite=drop_nonfinite)
        missing = [n for n in "xyz" if n not in (data.dtype.names or ())]
        raise FormatError(f"{path}: vertex element lacks property {', '.join(missing)} "
                          "(x, y and z are required)")
    if vertex.count == 0:
        raise FormatError(f"{path}: the vertex element is empty")
    bad, what = nonfinite_rows(data, positions)
    if bad.any():
        if not drop_nonfinite:
            raise FormatError(
                f"{path}: {int(bad.sum())} vertex(es) with NaN/Inf {what} (first at index "
                f"{int(np.flatnonzero(bad)[0])}); fix the file or load with drop_nonfinite=True "
                "(CLI: --drop-nonfinite)")
        source = _drop_vertices(source, path, bad)
        return model_from_source(source, path)

    faces = None
    face_el = source.element("face")
    if face_el is not None and face_el.count > 0:
        name = next((n for n in ("vertex_indices", "vertex_index")
                     if face_el.property(n) is not None), None)
        if name is not None:
            _require_list(path, "face", face_el.property(name))
            faces = _triangles_from_faces(face_el.data[name])
    strips = source.element("tristrips")
    if strips is not None and strips.count > 0 and strips.property("vertex_indices"):
        _require_list(path, "tristrips", strips.property("vertex_indices"))
        strip_tris = _triangles_from_strips(strips.data["vertex_indices"])
        faces = strip_tris if faces is None else np.concatenate([faces, strip_tris])
    if faces is not None and faces.size:
        if faces.min() < 0 or faces.max() >= vertex.count:
            raise FormatError(f"{path}: face indices out of range 0..{vertex.count - 1}")
    elif faces is not None:
        faces = None

    normals = _columns(data, ("nx", "ny", "nz"))
    if normals is not None and not np.any(normals):
        normals = None  # all-zero placeholder normals (common in 3DGS exports)
    colors = None
    rgb = _columns(data, ("red", "green", "blue"))
    if rgb is not None:
        colors = np.clip(rgb, 0, 255).astype(np.uint8)
    radius = next((data[n].astype(np.float64) for n in RADIUS_NAMES
                   if n in (data.dtype.names or ())), None)
    axes = _columns(data, AXIS_NAMES)
    if axes is not None:
        axes = axes.reshape(-1, 2, 3)
    gaussians = None
    names = data.dtype.names or ()
    if all(f"scale_{i}" in names for i in range(3)) and all(f"rot_{i}" in names for i in range(4)):
        rest = sorted((n for n in names if n.startswith("f_rest_")),
                      key=lambda n: int(n[7:]) if n[7:].isdigit() else 0)
        gaussians = Gaussians(
            scale_log=_shared(data, [f"scale_{i}" for i in range(3)]),
            rotation=_shared(data, [f"rot_{i}" for i in range(4)]),
            opacity=_shared(data, ["opacity"])[:, 0] if "opacity" in names else None,
            sh_dc=_shared(data, ["f_dc_0", "f_dc_1", "f_dc_2"]),
            sh_rest=_shared(data, rest) if rest else None,
        )
        if colors is None and gaussians.sh_dc is not None:
            from splatdeform.model import dc_to_colors

            colors = dc_to_colors(gaussians.sh_dc)
    kind = classify(has_faces=faces is not None, has_normals=normals is not None,
                    has_radius=radius is not None, has_axes=axes is not None,
                    has_gaussians=gaussians is not None)
    return PointModel(positions=positions, normals=normals, colors=colors, radius=radius,
                      axes=axes, faces=faces, gaussians=gaussians, kind=kind, source=source,
                      path=str(path))


# Properties of non-vertex elements that hold vertex indices (the standard PLY names).
VERTEX_REFS = ("vertex_indices", "vertex_index", "vertex1", "vertex2")


def _flatten(column: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Object column of 1-D arrays (R,) -> all values (M,) int64 and each row's length (R,)."""
    lengths = np.fromiter((len(v) for v in column), dtype=np.int64, count=len(column))
    flat = (np.concatenate([np.asarray(v, dtype=np.int64) for v in column]) if lengths.sum()
            else np.empty(0, dtype=np.int64))
    return flat, lengths


def _unflatten(flat: np.ndarray, lengths: np.ndarray, dtype: np.dtype) -> np.ndarray:
    column = np.empty(len(lengths), dtype=object)
    column[:] = np.split(flat.astype(dtype), np.cumsum(lengths)[:-1]) if len(lengths) else []
    return column


def _cut_strips(column: np.ndarray, bad: np.ndarray, remap: np.ndarray) -> np.ndarray:
    """Tristrip lists with the removed vertices turned into -1 separators (and remapped).

    A piece that resumes a strip at an odd position starts with its first vertex twice (one
    degenerate triangle, skipped by readers) so that its triangles keep their winding.
    """
    out = np.empty(len(column), dtype=object)
    for row, strip in enumerate(column):
        strip = np.asarray(strip, dtype=np.int64)
        removed = (strip >= 0) & bad[np.clip(strip, 0, len(bad) - 1)]
        if not removed.any():
            out[row] = np.where(strip >= 0, remap[np.clip(strip, 0, len(bad) - 1)], strip)\
                .astype(column[row].dtype)
            continue
        pieces: list[np.ndarray] = []
        seg_start = 0
        cuts = np.flatnonzero((strip < 0) | removed)
        start = 0
        for cut in [*cuts.tolist(), len(strip)]:
            piece = strip[start:cut]
            if len(piece) >= 3:
                if (start - seg_start) % 2:
                    piece = np.concatenate([piece[:1], piece])
                pieces.append(remap[piece])
            if cut < len(strip) and strip[cut] < 0:
                seg_start = cut + 1
            start = cut + 1
        joined = [x for p in pieces for x in (p, np.array([-1]))][:-1]
        out[row] = (np.concatenate(joined) if joined else np.empty(0, dtype=np.int64))\
            .astype(column[row].dtype)
    return out


def _drop_vertices(source: PlySource, path: str | Path, bad: np.ndarray) -> PlySource:
    """Remove vertices (bool mask ``bad`` (N,)) and keep every vertex reference consistent.

    Other elements' ``vertex_indices`` / ``vertex_index`` / ``vertex1`` / ``vertex2`` are
    remapped to the new numbering; references to a removed vertex: a ``face`` (or ``edge``, or
    any other element) row using one is dropped, a ``range_grid`` cell loses it (the grid keeps
    its shape), a ``tristrips`` strip is cut there.
    """
    n = len(bad)
    remap = np.cumsum(~bad) - 1
    elements = []
    for el in source.elements:
        data = el.data
        refs = [p for p in el.properties if p.name in VERTEX_REFS and p.dtype[0] in "iu"]
        if el.name == "vertex":
            data = data[~bad]
        elif refs and el.count:
            data = data.copy()
            drop_row = np.zeros(el.count, dtype=bool)
            lists = {}
            for p in refs:
                if p.is_list:
                    flat, lengths = _flatten(data[p.name])
                    outside = flat >= n  # in tristrips negative values separate strips
                    if el.name != "tristrips":
                        outside |= flat < 0
                    if outside.any():
                        raise FormatError(f"{path}: element '{el.name}' property '{p.name}' "
                                          f"has vertex indices outside 0..{n - 1}; cannot "
                                          "drop non-finite vertices consistently")
                    lists[p.name] = (flat, lengths)
                    if el.name not in ("range_grid", "tristrips"):
                        rows = np.repeat(np.arange(el.count), lengths)
                        drop_row |= np.bincount(rows, weights=bad[flat], minlength=el.count) > 0
                else:
                    column = data[p.name].astype(np.int64)
                    if ((column < 0) | (column >= n)).any():
                        raise FormatError(f"{path}: element '{el.name}' property '{p.name}' "
                                          f"has vertex indices outside 0..{n - 1}; cannot "
                                          "drop non-finite vertices consistently")
                    drop_row |= bad[column]
            for p in refs:
                if p.is_list and el.name == "tristrips":
                    data[p.name] = _cut_strips(data[p.name], bad, remap)
                elif p.is_list:
                    flat, lengths = lists[p.name]
                    if el.name == "range_grid":  # the cell stays, without the removed vertex
                        keep = ~bad[flat]
                        rows = np.repeat(np.arange(el.count), lengths)
                        lengths = np.bincount(rows[keep], minlength=el.count)
                        flat = flat[keep]
                    data[p.name] = _unflatten(remap[flat], lengths, np.dtype(p.dtype))
                else:
                    data[p.name] = remap[data[p.name].astype(np.int64)]
            data = data[~drop_row]
        # the text as read stays: unchanged rows keep it, and a save keeps the file's line end
        elements.append(PlyElementData(el.name, el.properties, data, el.ascii_text))
    return replace(source, elements=elements)


def read_model(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    """Load a PLY file as a PointModel (raises FormatError naming the file)."""
    return model_from_source(read_ply(path), path, drop_nonfinite=drop_nonfinite)


PLY_CODES = {"float": "f4", "double": "f8", "uchar": "u1"}


def _set_field(data: np.ndarray, props: list[PlyProperty], name: str, values: np.ndarray,
               type_name: str = "float") -> tuple[np.ndarray, list[PlyProperty]]:
    """Set (or append) scalar property ``name`` of the structured array ``data``."""
    if name in (data.dtype.names or ()):
        check_fits(f"PLY property {name}", values, data.dtype[name])
        data[name] = values.astype(data.dtype[name], copy=False)
        return data, props
    check_fits(f"PLY property {name}", values, PLY_CODES[type_name])
    code = PLY_CODES[type_name]
    descr = [(n, data.dtype[n]) for n in data.dtype.names] + [(name, code)]
    grown = np.empty(len(data), dtype=descr)
    for n in data.dtype.names:
        grown[n] = data[n]
    grown[name] = values
    return grown, props + [PlyProperty(name, code, type_name)]


def _plain_ply_input(model: PointModel) -> bool:
    """The model was read from a plain PLY file, whose own values (an opacity logit of +-inf
    included) a save keeps; a model decoded from a quantised splat file (``.splat``, SPZ,
    SOG, ``.ksplat``, compressed PLY, glTF) is written with
    :func:`~splatdeform.io.splats.finite_opacity` instead (alpha 0 / 1 as +-13.8155: every
    PLY reader keeps those splats, and each quantised writer turns them back into byte 0 /
    255)."""
    name = str(model.path or "").lower()
    return name.endswith(".ply") and not name.endswith(".compressed.ply")


def _save_columns(model: PointModel, names: tuple[str, ...]
                  ) -> list[tuple[str, np.ndarray, str, bool]]:
    """What a save writes into the vertex element, in order: (property name, values (N,),
    PLY type of a new property, ``changed``: an existing 3DGS field whose unchanged rows keep
    their bytes, so that a double-typed column keeps its untouched values bit-exact).
    ``names``: the source vertex element's fields (empty without a source)."""
    cols: list[tuple[str, np.ndarray, str, bool]] = []
    pos_type = "double" if model.source is None else "float"
    cols += [(axis, model.positions[:, i], pos_type, False) for i, axis in enumerate("xyz")]
    if model.normals is not None:
        cols += [(n, model.normals[:, i], "float", False)
                 for i, n in enumerate(("nx", "ny", "nz"))]
    if model.colors is not None and (model.source is None or "red" in names):
        cols += [(n, model.colors[:, i], "uchar", False)
                 for i, n in enumerate(("red", "green", "blue"))]
    if model.radius is not None:
        name = next((n for n in RADIUS_NAMES if n in names), "radius")
        cols.append((name, model.radius, "float", False))
    if model.axes is not None and (model.radius is None or "ux" in names):
        flat = model.axes.reshape(-1, 6)
        cols += [(n, flat[:, i], "float", False) for i, n in enumerate(AXIS_NAMES)]
    g = model.gaussians
    if g is not None:
        cols += [(f"scale_{i}", g.scale_log[:, i], "float", False) for i in range(3)]
        cols += [(f"rot_{i}", g.rotation[:, i], "float", False) for i in range(4)]
        # SH (rotated by deformations) and the other 3DGS fields: only changed rows are written
        opacity = g.opacity if g.opacity is None or _plain_ply_input(model) else \
            finite_opacity(g.opacity)   # alpha 0 / 1 of a quantised file: finite in a PLY
        extra = [("opacity", opacity)] if opacity is not None else []
        for part, prefix in ((g.sh_dc, "f_dc_"), (g.sh_rest, "f_rest_")):
            if part is not None:
                extra += [(f"{prefix}{i}", part[:, i]) for i in range(part.shape[1])]
        cols += [(name, values, "float", name in names) for name, values in extra]
    return cols


def _save_start(model: PointModel) -> tuple[PlySource, np.ndarray, list[PlyProperty]]:
    """(the source a save starts from, its vertex rows (not copied), their properties)."""
    if model.source is not None:
        source = model.source
        vertex = source.element("vertex")
        data, props = vertex.data, list(vertex.properties)
    else:
        source = PlySource(elements=[], comments=["written by splatdeform"], text=False,
                           byte_order="<")
        data, props = np.empty(model.n_points, dtype=[]), []
    if data.shape[0] != model.n_points:
        raise FormatError(f"model has {model.n_points} points but its PLY source "
                          f"{data.shape[0]} vertices; cannot save it verbatim")
    return source, data, props


def _elements(model: PointModel, source: PlySource, new_vertex: PlyElementData
              ) -> list[PlyElementData]:
    """The elements a save writes: the source's with ``new_vertex`` in place of its vertex
    element, or (no source) ``new_vertex`` and the model's triangles."""
    if model.source is not None:
        return [new_vertex if el.name == "vertex" else el for el in source.elements]
    elements = [new_vertex]
    if model.faces is not None and model.n_faces:
        column = np.empty(model.n_faces, dtype=object)
        column[:] = list(model.faces.astype(np.int32))
        face = np.empty(model.n_faces, dtype=[("vertex_indices", object)])
        face["vertex_indices"] = column
        elements.append(PlyElementData(
            "face", [PlyProperty("vertex_indices", "i4", "int", True, "u1", "uchar")], face))
    return elements


def source_for_save(model: PointModel) -> PlySource:
    """The PlySource a save writes: the verbatim source with the model's geometry written in."""
    source, data, props = _save_start(model)
    data = data.copy()
    for name, values, type_name, changed_only in _save_columns(model, data.dtype.names or ()):
        if changed_only:
            changed = data[name].astype(values.dtype) != values
            check_fits(f"PLY property {name}", values[changed], data.dtype[name])
            data[name][changed] = values[changed]
        else:
            data, props = _set_field(data, props, name, values, type_name)
    new_vertex = PlyElementData("vertex", props, data, None if model.source is None
                                else source.element("vertex").ascii_text)
    return replace(source, elements=_elements(model, source, new_vertex))


#: bytes of vertex records a binary save builds at a time (:func:`write_model`)
SAVE_BLOCK_BYTES = 4 << 20


def _save_plan(model: PointModel, data: np.ndarray, props: list[PlyProperty]
               ) -> tuple[list[tuple[str, np.ndarray, str, bool]], list[PlyProperty]] | None:
    """The columns and the output's vertex properties of a block-wise save, every value
    checked as :func:`source_for_save` checks it (the same refusal first); None where the
    rows cannot be written block by block (list properties, fields unlike their
    properties)."""
    names = data.dtype.names or ()
    if any(p.is_list for p in props) or names != tuple(p.name for p in props) or any(
            data.dtype[p.name].newbyteorder("=") != np.dtype(p.dtype) for p in props):
        return None
    cols = _save_columns(model, names)
    props = list(props)
    for name, values, type_name, changed_only in cols:
        what = f"PLY property {name}"
        if name not in names:
            check_fits(what, values, PLY_CODES[type_name])
            props.append(PlyProperty(name, PLY_CODES[type_name], type_name))
            continue
        try:
            check_fits(what, values, data.dtype[name])
        except FormatError:
            if not changed_only:
                raise
            changed = data[name].astype(values.dtype) != values   # only these are written
            check_fits(what, values[changed], data.dtype[name])
    return cols, props


def _write_blocks(out, data: np.ndarray, cols: list[tuple[str, np.ndarray, str, bool]],
                  dtype: np.dtype) -> None:
    """The vertex records ``dtype`` (the output's layout): the source's fields of ``data``
    with ``cols`` written in, built and written :data:`SAVE_BLOCK_BYTES` at a time into one
    reused buffer (the same bytes as :func:`source_for_save`'s whole element)."""
    n = data.shape[0]
    rows = max(1, SAVE_BLOCK_BYTES // max(dtype.itemsize, 1))
    buf = np.empty(min(rows, n), dtype=dtype)
    names = data.dtype.names or ()
    whole = {name for name, _, _, changed_only in cols if not changed_only}
    kept = [name for name in names if name not in whole]   # fields the columns leave as read
    for lo in range(0, n, rows):
        hi = min(lo + rows, n)
        block = buf[:hi - lo]
        for name in kept:
            block[name] = data[name][lo:hi]
        for name, values, _, changed_only in cols:
            part = values[lo:hi]
            if changed_only:
                changed = data[name][lo:hi].astype(values.dtype) != part
                block[name][changed] = part[changed].astype(data.dtype[name])
            elif name in names:
                block[name] = part.astype(data.dtype[name], copy=False)
            else:
                block[name] = part
        out.write(block.view(np.uint8))


def write_model(model: PointModel, stream, *, text: bool | None = None) -> None:
    """Write ``model`` as PLY to an open binary stream: a binary file's vertex records a
    block at a time (no whole copy of them), the same bytes as
    ``write_ply(source_for_save(model))``, which writes the rest (ascii files, list
    properties)."""
    source, data, props = _save_start(model)
    plan = None if (source.text if text is None else text) else _save_plan(model, data, props)
    if plan is None:
        write_ply(source_for_save(model), stream, text=text)
        return
    cols, props = plan
    bo = source.byte_order
    placeholder = PlyElementData("vertex", props, np.empty(model.n_points, dtype=[]))
    elements = _elements(model, source, placeholder)
    stream.write(header_text(replace(source, elements=elements), False, bo))
    for el in elements:
        if el is placeholder:
            _write_blocks(stream, data, cols,
                          np.dtype([(p.name, bo + p.dtype) for p in props]))
        else:
            _write_binary_element(stream, el, bo)


# ---- chunked access (streaming, Dask) ----------------------------------------------------

class PlyChunks(ChunkFile):
    """Binary PLY (either byte order) whose ``vertex`` element is the first element and holds
    scalar properties only, and that has no faces (``face``/``tristrips`` with rows); any other
    element after the vertices is copied verbatim into the output."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        with open(self.path, "rb") as f:
            head = f.read(MAX_HEADER_BYTES)
        header = parse_header(self.path, head)
        if header.text:
            raise InputError(f"{self.path}: streaming needs a binary PLY (this one is ascii); "
                             "raise --memory-budget or convert it to binary")
        if not header.elements or header.elements[0][0] != "vertex":
            raise InputError(f"{self.path}: streaming needs the 'vertex' element first")
        name, count, props = header.elements[0]
        if any(p.is_list for p in props):
            raise InputError(f"{self.path}: streaming needs scalar vertex properties")
        for el_name, el_count, _ in header.elements[1:]:
            if el_name in ("face", "tristrips") and el_count > 0:
                raise InputError(f"{self.path}: streaming handles point clouds; this is a mesh "
                                 f"({el_count} {el_name} rows): raise --memory-budget")
        self.header = header
        self.props = props
        self.n_points = count
        self.byte_order = header.byte_order
        self.dtype = np.dtype([(p.name, self.byte_order + p.dtype) for p in props])
        self.record_bytes = self.dtype.itemsize
        self.data_offset = header.size
        self.tail_offset = header.size + count * self.dtype.itemsize
        size = os.path.getsize(self.path)
        if size < self.tail_offset:
            raise FormatError(f"{self.path}: truncated binary body: {size} bytes, the vertex "
                              f"element needs {self.tail_offset}")
        missing = [a for a in "xyz" if a not in self.dtype.names]
        if missing:
            raise FormatError(f"{self.path}: vertex element lacks property {', '.join(missing)}")

    def rows(self, start: int, stop: int) -> np.ndarray:
        with open(self.path, "rb") as f:
            f.seek(self.data_offset + start * self.dtype.itemsize)
            rows = np.fromfile(f, dtype=self.dtype, count=stop - start)
        if rows.shape[0] != stop - start:
            raise FormatError(f"{self.path}: truncated binary body at vertex {start}")
        return rows

    def positions(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, 3) float64; a NaN/Inf or a far point is a FormatError (a stream
        cannot drop points)."""
        rows = self.rows(start, stop)
        out = np.empty((stop - start, 3), dtype=np.float64)
        for i, a in enumerate("xyz"):
            out[:, i] = rows[a]
        if not np.isfinite(out).all():
            bad = int(np.flatnonzero(~np.isfinite(out).all(axis=1))[0]) + start
            raise FormatError(f"{self.path}: vertex {bad} has NaN/Inf coordinates (streaming "
                              "cannot drop them; fix the file)")
        far = np.abs(out).max(axis=1) > MAX_COORDINATE if out.size else None
        if far is not None and far.any():
            bad = int(np.flatnonzero(far)[0]) + start
            raise FormatError(f"{self.path}: point {bad} at {out[bad - start].tolist()} is beyond "
                              f"+-{MAX_COORDINATE:g}; the fit would overflow; fix or crop the "
                              "file")
        return out

    def nonfinite(self, rows: np.ndarray) -> np.ndarray:
        return nonfinite_rows(rows)[0]

    def model_of(self, rows: np.ndarray) -> PointModel:
        source = PlySource([PlyElementData("vertex", self.props, rows)],
                           self.header.comments, self.header.obj_info, False, self.byte_order)
        return model_from_source(source, self.path)

    def encode(self, model: PointModel) -> tuple[np.ndarray, list[PlyProperty]]:
        vertex = source_for_save(model).element("vertex")
        dtype = np.dtype([(p.name, self.byte_order + p.dtype) for p in vertex.properties])
        return vertex.data.astype(dtype, copy=False), vertex.properties

    def header_bytes(self, props: list[PlyProperty], extra: int = 0) -> bytes:
        """The output header: vertex element with ``props`` (``extra`` more rows than read),
        the other elements as read."""
        elements = [PlyElementData("vertex", props,
                                   np.empty(self.n_points + extra, dtype=[]))]
        elements += [PlyElementData(n, p, np.empty(c, dtype=[]))
                     for n, c, p in self.header.elements[1:]]
        source = PlySource(elements, self.header.comments, self.header.obj_info, False,
                           self.byte_order)
        return header_text(source, False, self.byte_order)

    def copy_tail(self, out) -> None:
        """Copy the bytes after the vertex element (other elements) verbatim."""
        with open(self.path, "rb") as f:
            f.seek(self.tail_offset)
            while True:
                block = f.read(1 << 24)
                if not block:
                    break
                out.write(block)

    def writer(self, out: Path, props: list | None, extra: int = 0) -> PlyChunkWriter:
        return PlyChunkWriter(self, out, props, extra)


class PlyChunkWriter:
    """Streams vertex records into ``out``: the header first (``extra`` more vertices than
    the input's: split splats' children), the input's other elements verbatim at
    :meth:`close` (flushed to disk), after checking that the header's count was written."""

    def __init__(self, src: PlyChunks, out: Path, props: list[PlyProperty],
                 extra: int = 0) -> None:
        self.src = src
        self.expected, self.written = src.n_points + int(extra), 0
        # the atomic temporary file, which exists: never created here, so a writer that runs
        # after a Ctrl-C removed it cannot leave a new one behind (FileNotFoundError instead)
        self.stream = open(out, "r+b")
        self.stream.truncate(0)
        self.stream.write(src.header_bytes(props, int(extra)))

    def write(self, rows: np.ndarray) -> None:
        self.stream.write(np.ascontiguousarray(rows).view(np.uint8))  # no bytes copy
        self.written += len(rows)

    def close(self) -> None:
        if self.written != self.expected:   # the header's count is final: never a short file
            self.stream.close()
            raise ProcessingError(f"{self.src.path}: wrote {self.written:,} vertices, the "
                                  f"header counts {self.expected:,} (internal error)")
        self.src.copy_tail(self.stream)
        self.stream.flush()
        os.fsync(self.stream.fileno())
        self.stream.close()
