"""PlayCanvas ``.compressed.ply`` splats (SuperSplat / splat-transform) -> a standard 3DGS source.

The layout: a ``chunk`` element (one row per 256 splats: float min/max of position, log scale
and, in newer files, colour), a ``vertex`` element of four packed ``uint`` properties per splat
(``packed_position`` 11/10/11 bits, ``packed_rotation`` 2-bit index of the largest quaternion
component + three 10-bit others, ``packed_scale`` 11/10/11, ``packed_color`` RGBA 8 bits each) and
an optional ``sh`` element of ``uchar f_rest_*``. Decoding gives the usual INRIA 3DGS vertex
properties (x y z f_dc_0..2 opacity scale_0..2 rot_0..3 [f_rest_*], float); a save to ``.ply``
writes that plain 3DGS PLY, a save to ``.compressed.ply`` re-quantises (:func:`write_model`).
An 8-bit SH code v decodes to its bin centre ((v + 0.5) / 256 - 0.5) * 8. Axes as PLY space.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from splatdeform.model import SH_C0

from ..errors import FormatError
from ..model import PlyElementData, PlyProperty, PlySource

PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
CHUNK_BOUNDS = tuple(f"{m}_{a}" for m in ("min", "max") for a in "xyz") + tuple(
    f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz")
CHUNK_COLORS = tuple(f"{m}_{c}" for m in ("min", "max") for c in "rgb")
SPLATS_PER_CHUNK = 256
# an 8-bit opacity of 0 is alpha 0, a logit of -inf, and 255 is alpha 1, +inf (as the reference
# decoder, splat-transform, reads them); the clamp only keeps the other bytes' logit finite
OPACITY_EPS = 0.5 / 255
SH_RANGE = 8.0  # SH rest codes cover [-4, 4) in 256 bins
SCALE_CLAMP = 20.0  # log scales are clamped to +-20 before the chunk ranges are taken


def is_compressed(source: PlySource) -> bool:
    """True when the vertex element holds PlayCanvas packed properties instead of x y z."""
    vertex = source.element("vertex")
    return vertex is not None and "packed_position" in (vertex.data.dtype.names or ())


def _unorm(packed: np.ndarray, shift: int, bits: int) -> np.ndarray:
    mask = (1 << bits) - 1
    field = packed >> np.uint32(shift)
    field &= np.uint32(mask)
    out = field.astype(np.float64)
    out /= mask
    return out


def _lerp(chunk: np.ndarray, low: str, high: str, t: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """a * (1 - t) + b * t with a, b the splat's chunk bounds (in place: ``t`` is consumed)."""
    out = np.subtract(1.0, t)
    out *= chunk[low].astype(np.float64)[owner]
    t *= chunk[high].astype(np.float64)[owner]
    out += t
    return out


def _rotations(packed: np.ndarray) -> np.ndarray:
    """(N,) uint32 -> (N, 4) quaternions (rot_0..rot_3), the dropped largest one restored."""
    norm = np.sqrt(2.0)  # the other three lie in [-1/sqrt(2), 1/sqrt(2)]
    others = np.stack([(_unorm(packed, s, 10) - 0.5) * norm for s in (20, 10, 0)], axis=1)
    from .splats import restore_largest

    return restore_largest(others, (packed >> np.uint32(30)).astype(np.intp))


def _sh_codes(sh: PlyElementData, names: list[str]) -> np.ndarray:
    """(N, len(names)) codes of the sh element's ``names``: a uint8 view of the packed rows
    when every property is a uchar in that order (the layout writers use), else a copy."""
    data = sh.data
    dtype = data.dtype
    if data.flags.c_contiguous and dtype.itemsize == len(names) and \
            all(dtype.fields[m][0] == np.uint8 and dtype.fields[m][1] == j
                for j, m in enumerate(names)):
        return data.view(np.uint8).reshape(len(data), len(names))
    return np.stack([data[m] for m in names], axis=1) if names else \
        np.empty((len(data), 0), np.float32)


def decompress(source: PlySource, path: str | Path) -> PlySource:
    """The standard 3DGS PlySource of a PlayCanvas compressed file (raises FormatError naming
    the file when the layout is not the one described above)."""
    vertex = source.element("vertex")
    chunk_el = source.element("chunk")
    names = vertex.data.dtype.names or ()
    chunk_names = () if chunk_el is None else (chunk_el.data.dtype.names or ())
    missing = [n for n in PACKED if n not in names] + [
        n for n in CHUNK_BOUNDS if n not in chunk_names]
    if chunk_el is None or missing:
        raise FormatError(
            f"{path}: looks like a PlayCanvas compressed splat file (.compressed.ply) but "
            f"{'has no chunk element' if chunk_el is None else 'lacks ' + ', '.join(missing)}; "
            "this variant is not supported (decompress it with PlayCanvas splat-transform)")
    n = vertex.count
    chunk = chunk_el.data
    if chunk_el.count * SPLATS_PER_CHUNK < n:
        raise FormatError(f"{path}: PlayCanvas compressed file: {n} splats need "
                          f"{-(-n // SPLATS_PER_CHUNK)} chunks, the chunk element has "
                          f"{chunk_el.count}")
    if any(vertex.property(p).is_list or vertex.property(p).dtype[0] == "f" for p in PACKED):
        raise FormatError(f"{path}: PlayCanvas compressed file: packed_* must be integer "
                          "properties")
    sh = source.element("sh")
    names = []
    if sh is not None:
        if sh.count != n:
            raise FormatError(f"{path}: PlayCanvas compressed file: the sh element has "
                              f"{sh.count} rows for {n} splats")
        names = sorted((p.name for p in sh.properties
                        if p.name.startswith("f_rest_") and p.name[7:].isdigit()),
                       key=lambda name: int(name[7:]))
        if len(names) % 3:
            raise FormatError(f"{path}: PlayCanvas compressed file: {len(names)} f_rest "
                              "values per splat (a multiple of 3 expected)")
    from .splats import gaussian_table, table_source

    # decoded straight into the final float32 table (each value rounded once, from float64)
    table, out = gaussian_table(n, len(names))
    owner = np.arange(n) // SPLATS_PER_CHUNK
    packed = {p: vertex.data[p].astype(np.uint32) for p in PACKED}
    for i, (axis, (shift, bits)) in enumerate(zip("xyz", ((21, 11), (11, 10), (0, 11)),
                                                  strict=True)):
        out["positions"][:, i] = _lerp(chunk, f"min_{axis}", f"max_{axis}",
                                       _unorm(packed["packed_position"], shift, bits), owner)
        out["scale_log"][:, i] = _lerp(chunk, f"min_scale_{axis}", f"max_scale_{axis}",
                                       _unorm(packed["packed_scale"], shift, bits), owner)
    has_range = all(c in chunk_names for c in CHUNK_COLORS)
    for i, c in enumerate("rgb"):
        value = _unorm(packed["packed_color"], 24 - 8 * i, 8)
        if has_range:
            value = _lerp(chunk, f"min_{c}", f"max_{c}", value, owner)
        out["sh_dc"][:, i] = (value - 0.5) / SH_C0
    raw_alpha = _unorm(packed["packed_color"], 0, 8)
    alpha = np.clip(raw_alpha, OPACITY_EPS, 1 - OPACITY_EPS)
    out["opacity"][:, 0] = np.where(raw_alpha >= 1.0, np.inf,
                                    np.where(raw_alpha <= 0.0, -np.inf, -np.log(1 / alpha - 1)))
    del raw_alpha
    out["rotation"][:] = _rotations(packed["packed_rotation"])
    del packed, owner, alpha
    if names:
        rest = out["sh_rest"]  # ((v + 0.5) / 256 - 0.5) * 8 in place, exact in float32
        rest[:] = _sh_codes(sh, names)
        rest += np.float32(0.5)
        rest *= np.float32(SH_RANGE / 256)
        rest -= np.float32(SH_RANGE / 2)
    comments = [*source.comments, "decompressed from a PlayCanvas .compressed.ply by splatdeform"]
    return replace(table_source(table, comments), obj_info=list(source.obj_info),
                   quantised=source)


def _quantise(t: np.ndarray, bits: int) -> np.ndarray:
    mask = (1 << bits) - 1
    return np.clip(np.round(t * mask), 0, mask).astype(np.uint32)


def _chunk_ranges(values: np.ndarray, chunks: int) -> tuple[np.ndarray, np.ndarray]:
    """(N,) -> per-chunk (min, max) float32 of consecutive runs of 256 values."""
    pad = chunks * SPLATS_PER_CHUNK - len(values)
    grid = np.concatenate([values, np.full(pad, values[-1])]).reshape(chunks, -1)
    return grid.min(axis=1).astype(np.float32), grid.max(axis=1).astype(np.float32)


def _normalised(values: np.ndarray, low: np.ndarray, high: np.ndarray,
                owner: np.ndarray) -> np.ndarray:
    lo = low.astype(np.float64)[owner]
    span = high.astype(np.float64)[owner] - lo
    return np.where(span > 0, (values - lo) / np.where(span > 0, span, 1), 0.0)


def _pack3(columns: np.ndarray, prefix: str, chunk_cols: dict, owner: np.ndarray,
           chunks: int) -> np.ndarray:
    word = np.zeros(len(columns), dtype=np.uint32)
    for axis, bits, shift, column in zip("xyz", (11, 10, 11), (21, 11, 0), columns.T,
                                         strict=True):
        low, high = _chunk_ranges(column, chunks)
        chunk_cols[f"min_{prefix}{axis}"], chunk_cols[f"max_{prefix}{axis}"] = low, high
        word |= _quantise(_normalised(column, low, high, owner), bits) << np.uint32(shift)
    return word


def _rotation_words(quat: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions (w x y z) -> (N,) uint32: largest index + three 10-bit others."""
    n = len(quat)
    largest = np.argmax(np.abs(quat), axis=1)
    q = quat * np.where(quat[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]
    keep = np.ones((n, 4), dtype=bool)
    keep[np.arange(n), largest] = False
    others = q[keep].reshape(n, 3)
    word = largest.astype(np.uint32) << np.uint32(30)
    for i, shift in enumerate((20, 10, 0)):
        word |= _quantise(others[:, i] / np.sqrt(2.0) + 0.5, 10) << np.uint32(shift)
    return word


def compress(fields, comments: list[str]) -> PlySource:
    """The PlayCanvas compressed PlySource of ``fields`` (a :class:`~.splats.SplatFields`),
    splats in their given order, chunks of 256 consecutive splats."""
    from .splats import dc_to_color, normalised_quaternions, sigmoid, write_blocks

    n = fields.count
    chunks = -(-n // SPLATS_PER_CHUNK)
    owner = np.arange(n) // SPLATS_PER_CHUNK
    chunk_cols: dict[str, np.ndarray] = {}
    vertex = np.empty(n, dtype=[(p, "<u4") for p in PACKED])
    vertex["packed_position"] = _pack3(fields.positions, "", chunk_cols, owner, chunks)
    scale = np.clip(fields.scale_log.astype(np.float64), -SCALE_CLAMP, SCALE_CLAMP)
    vertex["packed_scale"] = _pack3(scale, "scale_", chunk_cols, owner, chunks)
    color = dc_to_color(fields.sh_dc)
    word = _quantise(sigmoid(fields.opacity), 8)
    for i, c in enumerate("rgb"):
        low, high = _chunk_ranges(color[:, i], chunks)
        chunk_cols[f"min_{c}"], chunk_cols[f"max_{c}"] = low, high
        word |= _quantise(_normalised(color[:, i], low, high, owner), 8) << np.uint32(24 - 8 * i)
    vertex["packed_color"] = word
    for rows in write_blocks(n):
        vertex["packed_rotation"][rows] = _rotation_words(
            normalised_quaternions(fields.rotation[rows]))
    order = [*CHUNK_BOUNDS[:6], *CHUNK_BOUNDS[6:], *CHUNK_COLORS]
    chunk = np.empty(chunks, dtype=[(c, "<f4") for c in order])
    for c in order:
        chunk[c] = chunk_cols[c]
    elements = [PlyElementData("chunk", [PlyProperty(c, "f4", "float") for c in order], chunk),
                PlyElementData("vertex", [PlyProperty(p, "u4", "uint") for p in PACKED], vertex)]
    rest = fields.sh_rest.reshape(n, -1)
    if rest.shape[1]:
        names = [f"f_rest_{i}" for i in range(rest.shape[1])]
        codes = np.empty(rest.shape, dtype=np.uint8)
        for rows in write_blocks(n):  # float32 temporaries of one block at a time
            block = np.multiply(rest[rows], np.float32(256 / SH_RANGE), dtype=np.float32)
            block += np.float32(128)
            np.floor(block, out=block)
            np.clip(block, 0, 255, out=block)
            codes[rows] = block
        sh = codes.view([(name, "u1") for name in names]).reshape(n)
        elements.append(PlyElementData("sh", [PlyProperty(m, "u1", "uchar") for m in names], sh))
    return PlySource(elements=elements, comments=comments, text=False, byte_order="<")


def _untouched_chunks(model, fields) -> np.ndarray | None:
    """(chunks,) bool: chunks whose every splat still has the values decoded from the model's
    compressed input (same count and order); None when the model has no such input."""
    from .splats import unchanged_rows

    if not isinstance(getattr(model.source, "quantised", None), PlySource):
        return None
    same = unchanged_rows(model, fields)
    if same is None:
        return None
    n = fields.count
    chunks = -(-n // SPLATS_PER_CHUNK)
    pad = np.concatenate([same, np.ones(chunks * SPLATS_PER_CHUNK - n, dtype=bool)])
    return pad.reshape(chunks, -1).all(axis=1)


def _keep_codes(out: PlySource, original: PlySource, keep: np.ndarray) -> None:
    """Copy the original chunk rows and splat codes of the ``keep`` chunks into ``out``."""
    n = out.element("vertex").count
    rows = np.repeat(keep, SPLATS_PER_CHUNK)[:n]
    chunk, old_chunk = out.element("chunk").data, original.element("chunk").data
    old_names = old_chunk.dtype.names or ()
    for name in chunk.dtype.names:
        if name in old_names:
            chunk[name][keep] = old_chunk[name][:len(keep)][keep]
        elif name.startswith(("min_", "max_")):  # no colour range in the input: plain 0..1
            chunk[name][keep] = 0.0 if name.startswith("min_") else 1.0
    vertex, old_vertex = out.element("vertex").data, original.element("vertex").data
    for name in PACKED:
        vertex[name][rows] = old_vertex[name][rows]
    sh, old_sh = out.element("sh"), original.element("sh")
    if sh is not None and old_sh is not None:
        for name in sh.data.dtype.names:
            sh.data[name][rows] = old_sh.data[name][rows]


def write_model(model, path: Path, stream) -> None:
    """Write ``model`` (3D Gaussian splats) as a PlayCanvas ``.compressed.ply`` to ``stream``."""
    from .ply_format import write_ply
    from .splats import fields_of, note_lossy

    fields = fields_of(model, path, ".compressed.ply")
    note_lossy(path, ".compressed.ply", "positions and log scales 11/10/11 bits within each "
               "256-splat chunk's range, colour and opacity 8 bits, rotation 10 bits per "
               "component, SH rest 8 bits in [-4, 4)", model)
    out = compress(fields, ["written by splatdeform (PlayCanvas compressed layout)"])
    keep = _untouched_chunks(model, fields)
    if keep is not None and keep.any():  # untouched chunks keep the input's bounds and codes
        _keep_codes(out, model.source.quantised, keep)
    write_ply(out, stream, text=False)
