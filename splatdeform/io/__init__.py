"""Loading and saving models, dispatched by file extension.

``load(path)`` never returns an empty model: it raises an :class:`~splatdeform.errors.InputError`
naming the file. ``save(model, path)`` writes atomically and refuses to overwrite the file the
model was loaded from.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import FormatError, InputError, ProcessingError
from ..model import PointModel
from .atomic import atomic_path, atomic_write, check_output_path
from .chunks import ChunkFile
from .declare import e57 as _e57
from .declare import las as _las
from .declare import pcd as _pcd
from .declare import ply as _ply
from .declare import splats as _splats
from .declare import xyz as _xyz
from .format import HEAD_BYTES, FileCost, Format, size_cost
from .regular import require_regular

SOG_META = _splats.SOG_META

#: Readers and writers in one table by extension, merged from the formats' declarations
#: (:mod:`splatdeform.io.declare`: a new format is one declaration there, and its reader module).
#: A double extension (``.compressed.ply``) is matched before the plain one; a key without a
#: leading dot (``meta.json``: a SOG folder) is a whole file name.
FORMATS: dict[str, Format] = {".ply": _ply.FORMATS[".ply"]}
#: extensions read here but never written -> why, and what to write instead
READ_ONLY: dict[str, str] = {}
for _declared in (_splats, _pcd, _xyz, _las, _e57):
    FORMATS.update(_declared.FORMATS)
    READ_ONLY.update(getattr(_declared, "READ_ONLY", {}))

SUPPORTED = tuple(FORMATS)
#: extensions the streaming / Dask paths read in chunks
STREAMABLE = tuple(ext for ext, fmt in FORMATS.items() if fmt.stream)
#: extensions whose files start with a PLY header (the batch probe reads their counts there)
PLY_EXTENSIONS = tuple(ext for ext in FORMATS if ext.endswith(".ply"))
LAS_EXTENSIONS = tuple(ext for ext, fmt in FORMATS.items() if fmt.module == "las")
#: extensions whose header probe counts the points (the others are judged from their size)
COSTED = tuple(ext for ext, fmt in FORMATS.items() if fmt.probe is not None)
#: LiDAR formats (z-up, elevation colours by default)
LIDAR_EXTENSIONS = tuple(ext for ext, fmt in FORMATS.items() if fmt.lidar)


def extension_of(path: str | Path) -> str:
    """The table key of ``path``: its double extension when the table has it, else its
    suffix (lower case; '' when none)."""
    name = Path(path).name.lower()
    if name in FORMATS:
        return name
    for ext in FORMATS:
        if ext.count(".") > 1 and name.endswith(ext) and len(name) > len(ext):
            return ext
    return Path(name).suffix


def split_extension(path: str | Path) -> tuple[str, str]:
    """(stem, extension) of ``path``'s name, by :func:`extension_of`: ``x.compressed.ply`` ->
    (``x``, ``.compressed.ply``), ``A.PLY`` -> (``A``, ``.ply``): the stem keeps its case, the
    extension is lower case. A whole-name key (``meta.json``) or a name without an extension
    gives (stem, suffix) as :class:`pathlib.Path` does."""
    name = Path(path).name
    ext = extension_of(name)
    if not ext.startswith(".") or not name.lower().endswith(ext) or len(name) <= len(ext):
        return Path(name).stem, Path(name).suffix.lower()
    return name[:-len(ext)], ext


def header_cost(name: str | Path, head: bytes, size: int, ext: str | None = None,
                file: str | Path | None = None) -> FileCost:
    """What the file ``name`` holds and what reading it costs, from its first bytes ``head`` (up
    to :data:`HEAD_BYTES`) and ``size``, by its format's declared probe (``ext``: the format's
    table key, default ``name``'s; ``file``: the file itself when there is one, for a probe
    that reads past ``head``). A format without a probe is judged from its size
    (:func:`~splatdeform.io.format.size_cost`). Raises the reader's FormatError/InputError line
    for a header it would refuse."""
    fmt = FORMATS.get((ext or extension_of(name)).lower())
    if fmt is None or fmt.probe is None:
        return size_cost(size)
    return fmt.probe(Path(name), head, size, None if file is None else Path(file))


def is_lidar(model: PointModel) -> bool:
    """A model read from a LiDAR format (LAS/LAZ), by its source or its path's extension."""
    source = FORMATS.get(_source_format(model) or "")
    return bool(source is not None and source.lidar) or \
        extension_of(model.path or "") in LIDAR_EXTENSIONS


def _source_format(model: PointModel) -> str | None:
    """The table key of the first format whose reader module built ``model.source``."""
    if model.source is None:
        return None
    module = type(model.source).__module__.rpartition(".")[2]
    return next((ext for ext, fmt in FORMATS.items() if fmt.module == module), None)


def open_chunks(path: str | Path) -> ChunkFile:
    """The chunk reader of ``path`` by its extension (InputError when not streamable)."""
    path = Path(path)
    ext = extension_of(path)
    fmt = FORMATS.get(ext)
    if fmt is None or fmt.chunks is None:
        raise InputError(f"{path}: streaming reads {', '.join(STREAMABLE)} (PLY binary); this "
                         f"{ext or 'extensionless'} file must fit the memory budget (raise "
                         "--memory-budget)")
    return fmt.chunks(path)


def format_fields(path: str | Path) -> dict:
    """The format's own fields for ``info`` (``format`` and ``format_fields``: SPZ version,
    glTF extensions, compressed-PLY chunks and SH bands, PCD encoding); {} for formats whose
    header ``describe`` already shows."""
    path = Path(path)
    if path.is_dir() and (path / SOG_META).is_file():
        path = path / SOG_META
    fmt = FORMATS.get(extension_of(path))
    return {} if fmt is None or fmt.fields is None else fmt.fields(path)


def _extension(path: Path, what: str) -> str:
    ext = extension_of(path)
    if ext not in FORMATS:
        raise InputError(f"{path}: unknown {what} extension {ext or '(none)'!r}; expected one of "
                         f"{', '.join(SUPPORTED)}")
    return ext


def check_writable(path: str | Path, what: str = "output") -> str:
    """The format key of output ``path`` (:func:`extension_of`) when this tool writes that
    format; InputError, one line naming ``path``, for an unknown extension or a format it only
    reads (:data:`READ_ONLY`). Called before any work and before any file or folder is made."""
    path = Path(path)
    ext = _extension(path, what)
    if ext in READ_ONLY:
        raise InputError(f"{path}: {READ_ONLY[ext]}")
    return ext


def load(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    """Load a model file (any extension of :data:`FORMATS`).

    Parameters
    ----------
    path : str or Path
        The model file; its extension picks the reader.
    drop_nonfinite : bool
        Drop vertices with NaN/Inf coordinates (and the faces using them) instead of raising.

    Returns
    -------
    PointModel
        Positions, normals, colours, faces, Gaussians and every other property the file holds.

    Raises
    ------
    InputError, FormatError
        One line naming the file.

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> path = sd.save(bumpy_bar(2000), "bar.ply")
    >>> model = sd.load("bar.ply")
    >>> model.n_points, model.positions.shape
    (2000, (2000, 3))
    """
    path = Path(path)
    if not path.exists():
        if path.is_symlink():
            raise InputError(f"{path}: is a symbolic link to nothing (dangling, or a loop); "
                             "expected a model file")
        raise InputError(f"{path}: no such file")
    if path.is_dir() and (path / SOG_META).is_file():
        path = path / SOG_META  # a SOG folder
    if path.is_dir():
        raise InputError(f"{path}: is a directory; expected a model file")
    require_regular(path)  # a FIFO or a device would block or never end
    ext = _extension(path, "model file")
    try:
        return FORMATS[ext].read(path, drop_nonfinite=drop_nonfinite)
    except PermissionError as exc:
        raise InputError(f"{path}: cannot read it (permission denied)") from exc
    except (FormatError, InputError):
        raise
    except (ValueError, IndexError, KeyError, OSError) as exc:
        raise FormatError(f"{path}: cannot read it: {exc}") from exc
    except MemoryError:
        raise ProcessingError(f"{path}: out of memory reading it "
                              f"({_declared(path)})") from None


def _declared(path: Path) -> str:
    """What ``path``'s header declares, for an out-of-memory line (its probe's count and load
    estimate), or why it could not be said."""
    import os

    from .regular import open_regular

    try:
        with open_regular(path) as fh:
            size = os.fstat(fh.fileno()).st_size
            head = fh.read(HEAD_BYTES)
        cost = header_cost(path, head, size, file=path)
    except Exception:  # noqa: BLE001 - the line is said whatever the probe meets
        return f"a {path.stat().st_size:,}-byte file"
    return (f"a {cost.size:,}-byte file declaring {cost.points:,} points, an estimated "
            f"{cost.load_bytes / 2**20:,.0f} MB to load")


def save(model: PointModel, path: str | Path, *, text: bool | None = None) -> Path:
    """Save atomically; the format follows the extension (PLY keeps the input's encoding unless
    ``text`` is given). Refuses to overwrite ``model.path``.

    Parameters
    ----------
    model : PointModel
        The model to write.
    path : str or Path
        The output file; its extension picks the writer (``.ply``, ``.las``, ``.spz``, ...).
    text : bool, optional
        PLY only: ascii (True) or binary (False); default: the input's encoding.

    Returns
    -------
    Path
        The written path.

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import sphere
    >>> sd.save(sphere(500), "ball.ply").name
    'ball.ply'
    >>> sd.load("ball.ply").n_points
    500
    """
    path = check_output_path(path, model.path)
    ext = check_writable(path)
    source = FORMATS.get(_source_format(model) or "")
    if source is not None and source.convert is not None and \
            FORMATS[ext].module != source.module:   # a source of its own, another format
        model = source.convert(model, ext)
    FORMATS[ext].write(model, path, text)
    return path


__all__ = ["FORMATS", "Format", "FileCost", "HEAD_BYTES", "load", "save", "SUPPORTED",
           "STREAMABLE", "PLY_EXTENSIONS", "LAS_EXTENSIONS", "COSTED", "LIDAR_EXTENSIONS",
           "SOG_META", "extension_of", "split_extension", "header_cost", "is_lidar",
           "format_fields", "atomic_path", "atomic_write", "check_output_path", "ChunkFile",
           "open_chunks", "check_writable", "READ_ONLY"]
