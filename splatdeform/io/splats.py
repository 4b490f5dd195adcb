"""The 3D Gaussian splat fields the quantised splat formats (.splat, .spz, .compressed.ply, ...)
encode, and their conversion to and from a :class:`PointModel` in PLY space.

PLY space is the INRIA 3DGS convention (x right, y down, z forward: RDF); every format module
converts its own axes to it on read and back on write, so comparisons are made in one frame.
A read builds a standard 3DGS vertex element (x y z f_dc_0..2 f_rest_* opacity scale_0..2
rot_0..3, float) and goes through the PLY model builder, so every loader shares one set of checks.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..model import SH_C0, PlyElementData, PlyProperty, PlySource, PointModel
from .checks import check_fits

#: SH rest coefficients per colour channel for each degree (4: SPZ v4 and PLY only)
SH_COEFFS = {0: 0, 1: 3, 2: 8, 3: 15, 4: 24}
#: the highest SH degree of the formats other than PLY and SPZ v4 (band 4 is dropped, said)
MAX_WRITE_DEGREE = 3
#: splats encoded at a time by the quantising writers (bounded float64 temporaries)
WRITE_BLOCK = 1 << 16


def write_blocks(n: int) -> list[slice]:
    """Consecutive slices of at most :data:`WRITE_BLOCK` splats covering ``range(n)``: a
    writer's per-splat float math, block by block (the codes are the same as in one go)."""
    return [slice(at, at + WRITE_BLOCK) for at in range(0, n, WRITE_BLOCK)]


class LossyWriteWarning(UserWarning):
    """A write into a quantised format: the message says which properties lose what."""


@dataclass
class SplatFields:
    """One splat scene in PLY space.

    positions: (N, 3) float64; scale_log: (N, 3) float32 (log standard deviations);
    rotation: (N, 4) float32 quaternion w, x, y, z (normalised on write);
    opacity: (N,) float32 logit; sh_dc: (N, 3) float32;
    sh_rest: (N, 3, K) float32, channel-major as in PLY's f_rest_* (K = 0, 3, 8 or 15).
    """

    positions: np.ndarray
    scale_log: np.ndarray
    rotation: np.ndarray
    opacity: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray

    @property
    def count(self) -> int:
        return len(self.positions)

    @property
    def sh_degree(self) -> int:
        return {k: d for d, k in SH_COEFFS.items()}[self.sh_rest.shape[2]]


def sh_degree_of(n_rest: int) -> int | None:
    """SH degree of a file with ``n_rest`` f_rest_* properties (None: not a 3DGS layout)."""
    for degree, k in SH_COEFFS.items():
        if n_rest == 3 * k:
            return degree
    return None


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, dtype=np.float64)))


def logit(p: np.ndarray, eps: float) -> np.ndarray:
    """Inverse sigmoid with ``p`` clamped to [eps, 1 - eps] (0 and 1 have no finite logit)."""
    p = np.clip(np.asarray(p, dtype=np.float64), eps, 1 - eps)
    return np.log(p / (1 - p))


#: the opacity logit a plain PLY holds where a splat is fully opaque or fully transparent
#: (alpha 1 / 0, an 8-bit opacity of 255 / 0): splat-transform's own clamp, alpha 1 -+ 1e-6.
#: Finite, so every PLY reader keeps the splat (splat-transform's ``-N`` drops a -inf opacity),
#: and quantised again it is byte 255 / 0 (sigmoid * 255 = 254.99974 / 0.00026).
FINITE_OPACITY = float(np.log((1 - 1e-6) / 1e-6))


def alpha_logit(alpha: np.ndarray) -> np.ndarray:
    """The one rule every 8-bit opacity is read by (``.splat``, SOG, SPZ, ``.ksplat``; the
    compressed PLY's own formula gives the same ends): alpha (N,) = byte / 255 in [0, 1] ->
    (N,) float64 logit, alpha 0 -> -inf, alpha 1 -> +inf, else the logit of alpha."""
    alpha = np.asarray(alpha, dtype=np.float64)
    return np.select([alpha >= 1.0, alpha <= 0.0], [np.inf, -np.inf],
                     logit(alpha, 0.5 / 255))


def finite_opacity(logits: np.ndarray) -> np.ndarray:
    """``logits`` (N,) with +-inf (alpha 1 / 0) as +-:data:`FINITE_OPACITY`, the other values
    unchanged (what a plain PLY written from a quantised splat file holds)."""
    logits = np.asarray(logits)
    if not np.isinf(logits).any():
        return logits
    return np.where(np.isinf(logits), np.copysign(FINITE_OPACITY, logits),
                    logits).astype(logits.dtype)


def dc_to_color(sh_dc: np.ndarray) -> np.ndarray:
    return 0.5 + SH_C0 * np.asarray(sh_dc, dtype=np.float64)


def color_to_dc(color: np.ndarray) -> np.ndarray:
    return (np.asarray(color, dtype=np.float64) - 0.5) / SH_C0


def normalised_quaternions(q: np.ndarray) -> np.ndarray:
    """(N, 4) -> (N, 4) float64 unit quaternions (a zero one becomes the identity)."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    out = np.where(norm > 0, q / np.where(norm > 0, norm, 1), 0.0)
    out[norm[:, 0] == 0, 0] = 1.0
    return out


def restore_largest(others: np.ndarray, which: np.ndarray) -> np.ndarray:
    """Smallest-three quaternions: (N, 3) float64 kept components (in order, the largest one
    left out) and (N,) its index 0..3 -> (N, 4) with the largest restored as
    sqrt(1 - |others|^2) (components keep the order the format stores them in)."""
    largest = np.sqrt(np.maximum(0.0, 1.0 - (others**2).sum(axis=1)))
    column = np.arange(4)[None, :]  # component c is others[c] before the index, others[c - 1] after
    pick = np.minimum(column - (column > which[:, None]), 2)
    quat = np.take_along_axis(others, pick, axis=1)
    quat[np.arange(len(which)), which] = largest
    return quat


def fields_of(model: PointModel, path: str | Path, fmt: str,
              max_degree: int = MAX_WRITE_DEGREE) -> SplatFields:
    """The splat fields a write of ``model`` to ``path`` (format name ``fmt``) encodes, SH
    above ``max_degree`` left out (the writer's :func:`note_lossy` says so); raises
    FormatError naming the file when the model is not a 3D Gaussian splat scene."""
    g = model.gaussians
    if g is None or g.opacity is None or g.sh_dc is None:
        raise FormatError(f"{path}: {fmt} holds 3D Gaussian splats; this {model.kind} model has "
                          "no scale_*/rot_*/opacity/f_dc_* fields (write .ply instead)")
    n = model.n_points
    rest = g.sh_rest if g.sh_rest is not None else np.zeros((n, 0), np.float32)
    if sh_degree_of(rest.shape[1]) is None:
        raise FormatError(f"{path}: {fmt} holds SH degrees 0-{max_degree} (0, 9, 24, 45 or 72 "
                          f"f_rest_* values); this model has {rest.shape[1]}")
    for name, values in (("positions", model.positions), ("scale_log", g.scale_log),
                         ("rotation", g.rotation), ("sh_dc", g.sh_dc), ("f_rest", rest)):
        try:
            check_fits(name, values, np.float32, fmt)
        except FormatError as exc:
            raise FormatError(f"{path}: {exc}") from None
    sh = rest.reshape(n, 3, -1)
    keep = SH_COEFFS[min(sh_degree_of(rest.shape[1]), max_degree)]
    if sh.shape[2] > keep:
        sh = sh[:, :, :keep]
    return SplatFields(positions=np.asarray(model.positions, dtype=np.float64),
                       scale_log=np.asarray(g.scale_log, dtype=np.float32),
                       rotation=np.asarray(g.rotation, dtype=np.float32),
                       opacity=np.asarray(g.opacity, dtype=np.float32),
                       sh_dc=np.asarray(g.sh_dc, dtype=np.float32),
                       sh_rest=sh.astype(np.float32, copy=False))


def unchanged_rows(model: PointModel, fields: SplatFields) -> np.ndarray | None:
    """(N,) bool: splats whose fields still equal the values decoded from the model's quantised
    input (its PLY source's vertex element, same count and order); None when the model has no
    quantised input or a different count or SH layout."""
    source = model.source
    decoded = None if source is None else source.element("vertex")
    if getattr(source, "quantised", None) is None or decoded is None or \
            decoded.count != fields.count:
        return None
    data = decoded.data
    names = data.dtype.names or ()
    n = fields.count
    rest = fields.sh_rest.reshape(n, -1)
    n_rest = sum(1 for m in names if m.startswith("f_rest_"))
    if n_rest != rest.shape[1]:
        return None
    same = np.ones(n, dtype=bool)
    for cols, values in ((list("xyz"), fields.positions.astype(np.float32)),
                         ([f"scale_{i}" for i in range(3)], fields.scale_log),
                         ([f"rot_{i}" for i in range(4)], fields.rotation),
                         (["opacity"], fields.opacity[:, None]),
                         ([f"f_dc_{i}" for i in range(3)], fields.sh_dc),
                         ([f"f_rest_{i}" for i in range(n_rest)], rest)):
        for j, name in enumerate(cols):
            same &= data[name] == values[:, j]
    return same


def dropped_properties(model: PointModel) -> list[str]:
    """Vertex properties of the model's source that no splat format holds (named in the
    lossy-write note: normals, colours, custom fields ...)."""
    if model.source is None or model.source.element("vertex") is None:
        return []
    names = model.source.element("vertex").data.dtype.names or ()
    known = {"x", "y", "z", "opacity", *(f"scale_{i}" for i in range(3)),
             *(f"rot_{i}" for i in range(4)), *(f"f_dc_{i}" for i in range(3))}
    return [n for n in names if n not in known and not n.startswith("f_rest_")]


def note_lossy(path: str | Path, fmt: str, losses: str | None, model: PointModel,
               sh_kept: int | None = None) -> None:
    """Say once for this write which properties the format quantises or drops (``losses``
    None: a format that keeps float32 values says something only when it drops properties;
    ``sh_kept``: the f_rest_* values the format holds, default those of degree 3)."""
    dropped = dropped_properties(model)
    g = model.gaussians
    if losses is None and g is not None and g.sh_rest is not None and \
            g.sh_rest.shape[1] > (3 * SH_COEFFS[MAX_WRITE_DEGREE] if sh_kept is None
                                  else sh_kept):
        losses = "float32 values kept"
    if losses is None:
        if not dropped:
            return
        losses = "float32 values kept"
    g = model.gaussians
    n_rest = 0 if g is None or g.sh_rest is None else g.sh_rest.shape[1]
    if sh_kept is None:  # band 4 (72 values) is held by PLY and SPZ v4 only
        sh_kept = 3 * SH_COEFFS[MAX_WRITE_DEGREE]
    if n_rest > sh_kept:
        dropped.append(f"f_rest_{sh_kept}..f_rest_{n_rest - 1} (SH above what {fmt} holds)")
    text = f"{path}: {fmt} is lossy: {losses}"
    if dropped:
        text += f"; not kept: {', '.join(dropped)}"
    warnings.warn(text, LossyWriteWarning, stacklevel=3)


FIELD_ORDER = ("positions", "sh_dc", "sh_rest", "opacity", "scale_log", "rotation")
FIELD_WIDTH = {"positions": 3, "sh_dc": 3, "opacity": 1, "scale_log": 3, "rotation": 4}


def gaussian_names(n_rest: int) -> list[str]:
    """The standard 3DGS vertex property names with ``n_rest`` f_rest_* values."""
    return [*"xyz", *(f"f_dc_{i}" for i in range(3)), *(f"f_rest_{i}" for i in range(n_rest)),
            "opacity", *(f"scale_{i}" for i in range(3)), *(f"rot_{i}" for i in range(4))]


def gaussian_table(n: int, n_rest: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """An empty (N, 14 + n_rest) float32 table in the standard 3DGS property order and, by
    field name (:data:`FIELD_ORDER`), its (N, width) column views: a decoder writes each decoded
    field straight into them (no intermediate float arrays), then calls :func:`table_source`."""
    table = np.empty((n, 14 + n_rest), dtype="<f4")
    views, at = {}, 0
    for name in FIELD_ORDER:
        width = n_rest if name == "sh_rest" else FIELD_WIDTH[name]
        views[name] = table[:, at:at + width]
        at += width
    return table, views


def table_source(table: np.ndarray, comments: list[str]) -> PlySource:
    """The 3DGS PlySource viewing a :func:`gaussian_table` (no copy)."""
    names = gaussian_names(table.shape[1] - 14)
    data = table.view([(name, "<f4") for name in names]).reshape(len(table))
    props = [PlyProperty(name, "f4", "float") for name in names]
    return PlySource(elements=[PlyElementData("vertex", props, data)], comments=comments,
                     text=False, byte_order="<")


def gaussian_source(fields: SplatFields, comments: list[str], *,
                    release: bool = False) -> PlySource:
    """The standard 3DGS PlySource (x y z f_dc_* f_rest_* opacity scale_* rot_*, float).

    release: drop each of ``fields``' arrays once copied (a reader's decode is not needed
    after this, so its memory is free before the model copies the Gaussian columns)."""
    n = fields.count
    k = fields.sh_rest.shape[1] * fields.sh_rest.shape[2] if fields.sh_rest.ndim == 3 else \
        fields.sh_rest.shape[1]
    table, views = gaussian_table(n, k)  # filled by contiguous blocks, then viewed
    for name in FIELD_ORDER:
        views[name][:] = getattr(fields, name).reshape(n, -1)
        if release:
            setattr(fields, name, np.empty((0,) * getattr(fields, name).ndim, np.float32))
    return table_source(table, comments)


def read_bytes(path: str | Path, limit: int = 1 << 34) -> bytes:
    """The whole file, through the one opener (a regular file: a FIFO or a device is refused
    without blocking), refusing one larger than ``limit`` bytes before reading it."""
    from .regular import read_regular

    return read_regular(path, max_bytes=limit, what="splat file")
