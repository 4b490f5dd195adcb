"""``splatdeform convert IN OUT``: any readable format to any writable one, with an optional
whole-scene similarity (rotation, uniform scale, translation) applied exactly.

The transform flags take PlayCanvas splat-transform's convention, measured with the pinned
3.7.0 (``splat-transform IN -r X,Y,Z -s S -t X,Y,Z OUT``), so the same numbers give the same
scene in both tools:

- Euler angles in degrees, applied about the fixed axes x first, then y, then z
  (R = Rz(z) Ry(y) Rx(x));
- in splat-transform's frame, which is the file's (PLY) frame turned 180 degrees about z:
  F = diag(-1, -1, 1), so in file coordinates the rotation is F R F and the translation F t
  (a rotation about z is the same in both; about x or y the file sees the opposite angle, and
  a translation's x and y change sign);
- the order: rotate, then scale (about the origin), then translate.

Applied exactly (float64, one similarity J = s R for every point): positions p' = s R p + t;
normals R n; surfel axes s R u; radius-only surfels' radii times s; 3D Gaussians: log scales
+ ln s, quaternions R q (Hamilton product, |q| kept), SH bands 1..3 rotated by R
(:func:`splatdeform.geometry.rotate_sh_rest`). Nothing else changes; with no transform the
output is the plain load + save (byte-identical where the format round-trips).

Streamed (chunks through the format's chunk reader, :func:`splatdeform.io.open_chunks`) when
the in-memory estimate exceeds the memory budget (:func:`splatdeform.memory.choose`) and the
input and output are the same streamable format (binary PLY, LAS, LAZ); otherwise in memory,
and refused with one line over an explicit budget.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import FormatError, InputError
from .model import MAX_SCALE, MIN_SCALE, PointModel

#: splat-transform's frame is the file's turned 180 degrees about z (measured with 3.7.0)
FRAME = np.diag([-1.0, -1.0, 1.0])
#: bytes a converted point costs beside its load: the transformed copy and the encoded output
CONVERT_BYTES_PER_POINT = 64


@dataclass(frozen=True)
class Similarity:
    """x -> scale * rotation @ x + translation, in the model's (file's) coordinates."""

    rotation: np.ndarray
    scale: float = 1.0
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def identity(self) -> bool:
        return bool((self.rotation == np.eye(3)).all() and self.scale == 1.0
                    and not np.any(self.translation))

    @property
    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m


def euler_matrix(x: float, y: float, z: float) -> np.ndarray:
    """Rz(z) Ry(y) Rx(x) for angles in degrees (right-handed, about fixed axes x, y, z)."""
    cx, sx = math.cos(math.radians(x)), math.sin(math.radians(x))
    cy, sy = math.cos(math.radians(y)), math.sin(math.radians(y))
    cz, sz = math.cos(math.radians(z)), math.sin(math.radians(z))
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def similarity(rotate_euler: tuple[float, float, float] | None = None, scale: float | None = None,
               translate: tuple[float, float, float] | None = None) -> Similarity:
    """The file-frame similarity of splat-transform's ``-r X,Y,Z -s S -t X,Y,Z`` (each
    optional; see the module docstring for the convention)."""
    rot = np.eye(3) if rotate_euler is None else FRAME @ euler_matrix(*rotate_euler) @ FRAME
    s = 1.0 if scale is None else float(scale)
    t = np.zeros(3) if translate is None else FRAME @ np.asarray(translate, dtype=np.float64)
    return Similarity(rot, s, t)


def parse_triple(text: str, flag: str) -> tuple[float, float, float]:
    """``"X,Y,Z"`` -> three finite floats (InputError naming ``flag`` otherwise)."""
    parts = str(text).split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise InputError(f"{flag}: expected three finite numbers X,Y,Z, got {text!r}")
    return values  # type: ignore[return-value]


def parse_scale(text: str, flag: str = "--scale") -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and MIN_SCALE <= value <= MAX_SCALE):
        raise InputError(f"{flag}: expected a number between {MIN_SCALE:g} and {MAX_SCALE:g} "
                         f"(as handle scales; a smaller or larger one collapses or overflows "
                         f"the model), got {text!r}")
    return value


def transform_model(model: PointModel, sim: Similarity) -> PointModel:
    """A copy of ``model`` moved by ``sim`` (the model itself when ``sim`` is the identity).
    Raises InputError when a moved value no longer fits the output's number type."""
    if sim.identity:
        return model
    from .deform.model_apply import check_finite
    from .geometry import matrix_to_quaternion, quaternion_multiply, rotate_sh_rest

    out = model.copy()
    r, s = sim.rotation, sim.scale
    with np.errstate(over="ignore", invalid="ignore"):
        out.positions[:] = (np.asarray(model.positions, dtype=np.float64) @ (s * r).T
                            + sim.translation).astype(out.positions.dtype)
        if model.normals is not None:
            out.normals[:] = (np.asarray(model.normals, np.float64) @ r.T).astype(
                out.normals.dtype)
        if model.axes is not None:
            axes = np.asarray(model.axes, np.float64).reshape(-1, 2, 3) @ (s * r).T
            out.axes[:] = axes.reshape(out.axes.shape).astype(out.axes.dtype)
        elif model.radius is not None:
            out.radius[:] = (np.asarray(model.radius, np.float64) * s).astype(out.radius.dtype)
        g = model.gaussians
        if g is not None:
            og = out.gaussians
            og.scale_log[:] = (g.scale_log.astype(np.float64) + math.log(s)).astype(
                og.scale_log.dtype)
            q_r = matrix_to_quaternion(r[None])
            og.rotation[:] = quaternion_multiply(q_r, g.rotation.astype(np.float64)).astype(
                og.rotation.dtype)
            if g.sh_rest is not None and g.sh_rest.shape[1] and not (r == np.eye(3)).all():
                og.sh_rest[:] = rotate_sh_rest(g.sh_rest, np.broadcast_to(r, (len(g.sh_rest),
                                                                              3, 3)))
    check_finite(model, out)
    return out


def convert_bytes(path: str | Path) -> int:
    """The in-memory convert's estimated peak (bytes, interpreter included)."""
    from .memory import BASE_BYTES, file_cost

    cost = file_cost(path)
    return BASE_BYTES + cost.load_bytes + cost.points * (cost.record_bytes +
                                                         CONVERT_BYTES_PER_POINT)


def convert(src: str | Path, dst: str | Path, sim: Similarity | None = None, *,
            budget: int | None = None, drop_nonfinite: bool = False,
            log: Callable[[str], None] | None = None) -> str:
    """Convert ``src`` to ``dst`` (formats by extension), moved by ``sim``.

    Parameters
    ----------
    src : str or Path
        The input model (any readable format).
    dst : str or Path
        The output file (never the input); its extension picks the writer.
    sim : Similarity, optional
        The whole-scene similarity, e.g. :func:`similarity` of splat-transform's ``-r``,
        ``-s``, ``-t`` (see the module docstring); None: no transform (load + save).
    budget : int, optional
        An explicit memory budget in bytes (a cap: stream or refuse); None: half the RAM.
    drop_nonfinite : bool
        Drop vertices with NaN/Inf coordinates instead of raising.
    log : callable, optional
        Receives the one-line note when the budget decided how it runs.

    Returns
    -------
    str
        ``"memory"`` or ``"stream"``: how it ran.

    Raises
    ------
    InputError
        One line: an unknown extension, the output is the input, over an explicit budget.

    Examples
    --------
    >>> import splatdeform as sd
    >>> from splatdeform.conversion import convert, similarity
    >>> from data_tools.synth import gaussian_bar
    >>> _ = sd.save(gaussian_bar(1000), "bar.ply")
    >>> convert("bar.ply", "bar.splat")
    'memory'
    >>> convert("bar.ply", "bar_up.ply", similarity(translate=(0, 0, 2), scale=0.5))
    'memory'
    >>> before, after = sd.load("bar.ply"), sd.load("bar_up.ply")
    >>> bool(abs(after.positions - (0.5 * before.positions + [0, 0, 2])).max() < 1e-5)
    True
    """
    from . import memory
    from .io import FORMATS, STREAMABLE, SUPPORTED, check_writable, extension_of, load, save
    from .io.plan import plan_io

    src, dst = Path(src), Path(dst)
    sim = sim or similarity()
    plan_io([("input", src)], [("output", dst)])
    ext_in, ext_out = extension_of(src), extension_of(dst)
    if ext_out not in FORMATS:
        raise InputError(f"output {dst}: unknown extension {ext_out or '(none)'!r}; expected "
                         f"one of {', '.join(SUPPORTED)}")
    check_writable(dst)   # a format only read here: refused before any work or folder
    if src.is_file() and ext_in not in FORMATS:
        raise InputError(f"input {src}: unknown extension {ext_in or '(none)'!r}; expected "
                         f"one of {', '.join(SUPPORTED)}")
    mode = "memory"
    if src.is_file() and ext_in in FORMATS:
        same = ext_in == ext_out and ext_in in STREAMABLE
        choice = memory.choose(convert_bytes(src), budget, streamable=same,
                               name=src, whole="--drop-nonfinite" if drop_nonfinite else None,
                               why_not=f"streaming converts {', '.join(STREAMABLE)} to the "
                                       "same format only")
        if choice.mode == "refuse":
            raise InputError(choice.message)
        mode = choice.mode
        if choice.message and log is not None:
            log(choice.message)
    if mode == "stream":
        _stream(src, dst, sim, budget or memory.default_budget())
    elif not (sim.identity and not drop_nonfinite and ext_in == ext_out == ".ply"
              and _copy_ply(src, dst)):
        save(transform_model(load(src, drop_nonfinite=drop_nonfinite), sim), dst)
    return mode


def _copy_ply(src: Path, dst: Path) -> bool:
    """A binary PLY point cloud converted to PLY with no transform, chunk by chunk: the load +
    save's bytes at close to the speed of reading the file (small chunks stay in the CPU
    caches; a whole load + save of 5M points took 4x a bare numpy read-modify-write). Where
    the file's property types make the load + save of a record its own bytes
    (:func:`_verbatim_checks`), a chunk's records are written as read once they pass the
    load's checks; otherwise (and for a chunk holding a NaN the save could change) each chunk
    goes through the chunk model and back. False, with nothing written, where the chunk
    reader does not take the file (ascii, a mesh, list properties, no points) or a chunk fails:
    the whole load then runs and gives its own error (a NaN's index counted over the file, not
    the chunk)."""
    from .io import open_chunks
    from .io.chunks import map_chunks
    from .memory import STREAM_CHUNK_MAX

    try:
        chunks = open_chunks(src)
    except Exception:   # noqa: BLE001 - the whole load reports it
        return False
    if chunks.n_points == 0:
        chunks.close()
        return False
    chunk = max(8_192, min(STREAM_CHUNK_MAX, (2 << 20) // max(chunks.record_bytes, 1)))
    checks = _verbatim_checks(chunks.dtype)

    def verbatim(a: int, b: int) -> tuple[np.ndarray, list]:
        fh.seek(chunks.data_offset + a * chunks.record_bytes)   # the chunks come in order
        rows = np.fromfile(fh, dtype=chunks.dtype, count=b - a)
        if len(rows) != b - a:
            raise FormatError(f"{src}: truncated binary body at vertex {a}")
        if _rows_verbatim(chunks, rows, *checks):
            return rows, chunks.props
        return chunks.encode(chunks.model_of(rows))   # raises the load's error, if any

    try:
        if checks is None:
            map_chunks(chunks, dst, lambda a, b: chunks.encode(chunks.read(a, b)), chunk,
                       read_ahead=True)
        else:
            with open(src, "rb") as fh:   # one handle for every chunk
                map_chunks(chunks, dst, verbatim, chunk)
    except Exception:   # noqa: BLE001 - nothing written (atomic): the whole load says why
        return False
    return True


#: the vertex properties a PLY load reads into the model and its save writes back (positions,
#: normals, radius, surfel axes) through float64: exact for every PLY type, NaN payloads aside
_FLOAT64_FIELDS = ("x", "y", "z", "nx", "ny", "nz", "radius", "surfel_radius",
                   "ux", "uy", "uz", "vx", "vy", "vz")


def _verbatim_checks(dtype: np.dtype) -> tuple[tuple[str, ...], tuple[str, ...], bool] | None:
    """When the identity load + save of binary PLY records of ``dtype`` gives their own bytes
    (io/ply.py's ``model_from_source`` and ``source_for_save``): what to check in each chunk,
    as (float x/y/z fields: must be finite, float fields read through float64 other than x/y/z:
    a NaN there goes the chunk model's way (a signalling NaN comes back quiet), whether the
    records hold 3DGS fields (their finiteness is the load's own check)); None where a type
    makes the save change a value: colours not uchar (the model holds them as clipped uint8),
    3DGS log-scales or rotations not float32 (the model holds them as float32), a 64-bit
    integer (not exact in float64)."""
    names = dtype.names or ()
    if any(dtype[n].kind not in "fiu" or (dtype[n].kind != "f" and dtype[n].itemsize > 4)
           for n in names):
        return None
    rgb = ("red", "green", "blue")
    if all(c in names for c in rgb) and any(dtype[c] != np.dtype("u1") for c in rgb):
        return None
    splat = [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    if all(n in names for n in splat) and any(dtype[n].base.str[1:] != "f4" for n in splat):
        return None
    floats = [n for n in _FLOAT64_FIELDS if n in names and dtype[n].kind == "f"]
    xyz = ("x", "y", "z")
    return (tuple(n for n in floats if n in xyz), tuple(n for n in floats if n not in xyz),
            any(n.startswith("scale_") for n in names))


def _rows_verbatim(chunks, rows: np.ndarray, xyz: tuple[str, ...], nan_free: tuple[str, ...],
                   splat: bool) -> bool:
    """The records ``rows`` pass the load's checks (finite coordinates and 3DGS fields) and
    come back from the load + save as they are (no NaN in ``nan_free``)."""
    if splat:
        if chunks.nonfinite(rows).any():
            return False
    elif not all(np.isfinite(rows[n]).all() for n in xyz):
        return False
    return not any(np.isnan(rows[n]).any() for n in nan_free)


def _stream(src: Path, dst: Path, sim: Similarity, budget: int) -> None:
    """Chunk by chunk through the input format's chunk reader and writer (same format), by
    the one chunk loop (:func:`splatdeform.io.chunks.map_chunks`)."""
    from .io import open_chunks
    from .io.chunks import map_chunks
    from .memory import BASE_BYTES, stream_chunk

    chunks = open_chunks(src)
    map_chunks(chunks, dst,
               lambda a, b: chunks.encode(transform_model(chunks.read(a, b), sim)),
               stream_chunk(budget, chunks.record_bytes, BASE_BYTES), read_ahead=True)
