"""Loading and saving models, dispatched by file extension.

``load(path)`` never returns an empty model: it raises an :class:`~splatdeform.errors.InputError`
naming the file. ``save(model, path)`` writes atomically and refuses to overwrite the file the
model was loaded from.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from types import ModuleType

from ..errors import FormatError, InputError
from ..model import PointModel
from .atomic import atomic_path, atomic_write, check_output_path
from .chunks import ChunkFile
from .regular import require_regular


@dataclass(frozen=True)
class Format:
    """One file format, by the module of this package that reads it (``read_model(path,
    drop_nonfinite=) -> PointModel``) and writes it; the module is imported on first use, so a
    load imports only its own format's module. ``writer``: the writing module when another
    (None: ``module``); ``write_by``: how it is called (``stream``: ``write_model(model, path,
    stream)`` into an atomic stream; ``path``: ``write_model(model, tmp_path)``; ``ply``:
    ``write_model(model, stream, text=)``; ``folder``: ``write_folder(model, path)``);
    ``chunk_class``: the module's ChunkFile class for the streaming and Dask paths (None: not
    streamable); ``lossy``: a write quantises (and says once what it loses); ``fields``: the
    format's own fields for ``info`` (None: its header shows them)."""

    module: str
    write_by: str = "stream"
    writer: str | None = None
    chunk_class: str | None = None
    lossy: bool = False
    fields: Callable[[Path], dict] | None = None

    @staticmethod
    def _load(name: str) -> ModuleType:
        return importlib.import_module(f"{__name__}.{name}")

    @property
    def read(self):
        """``read_model`` of the format's module."""
        return self._load(self.module).read_model

    @property
    def chunks(self) -> type[ChunkFile] | None:
        """The chunk reader class (None: not streamable)."""
        return None if self.chunk_class is None else getattr(self._load(self.module),
                                                             self.chunk_class)

    @property
    def stream(self) -> bool:
        """True when the streaming and Dask paths read this format in chunks."""
        return self.chunk_class is not None

    def write(self, model: PointModel, path: Path, text: bool | None) -> None:
        """Write ``model`` to ``path`` atomically (``text``: PLY encoding, None: the input's)."""
        module = self._load(self.writer or self.module)
        if self.write_by == "folder":
            module.write_folder(model, path)
        elif self.write_by == "path":
            with atomic_path(path) as tmp:
                module.write_model(model, tmp)
        else:
            with atomic_write(path) as stream:
                if self.write_by == "ply":
                    module.write_model(model, stream, text=text)
                else:
                    module.write_model(model, path, stream)


def _compressed_ply_fields(path: Path) -> dict:
    from . import ply

    source = ply.read_ply(path)
    chunk, sh = source.element("chunk"), source.element("sh")
    n_rest = 0 if sh is None else len(sh.properties)
    return {"format": "PlayCanvas compressed PLY", "format_fields": {
        "chunks": 0 if chunk is None else chunk.count, "sh_bands": {0: 0, 9: 1, 24: 2, 45: 3}
        .get(n_rest, n_rest)}}


def _spz_fields(path: Path) -> dict:
    from . import spz

    h = spz.read_info(path)
    return {"format": f"SPZ v{h['version']} (gzip)", "format_fields": {
        "version": h["version"], "sh_degree": h["sh_degree"],
        "fractional_bits": h["fractional_bits"], "antialiased": h["antialiased"]}}


def _gltf_fields(path: Path) -> dict:
    from . import gltf

    doc, _ = gltf.read_document(path)
    used = doc.get("extensionsUsed", [])
    return {"format": "glTF 2.0 " + ("binary (.glb)" if path.suffix.lower() == ".glb" else
                                     "JSON (.gltf)"),
            "format_fields": {"extensions": ", ".join(used) or "none",
                              "generator": doc.get("asset", {}).get("generator", "?")}}


def _pcd_fields(path: Path) -> dict:
    from . import pcd

    source, _ = pcd.read_source(path)
    return {"format": f"PCD DATA {source.encoding}", "format_fields": {
        "version": dict(source.header).get("VERSION", "?"), "width": source.width,
        "height": source.height, "fields": " ".join(source.fields)}}


def _sog_fields(path: Path) -> dict:
    from . import sog

    h = sog.read_info(path)
    return {"format": f"PlayCanvas SOG v{h['version']} "
            + ("bundle (.sog)" if path.suffix.lower() == ".sog" else "folder (meta.json)"),
            "format_fields": {"sh_bands": h["sh_bands"], "palette": h["palette"],
                              "antialias": h["antialias"], "generator": h["generator"]}}


#: a SOG folder's file (the table's whole-name key)
SOG_META = "meta.json"
_SPLATS = {"lossy": True}

#: Readers and writers in one table by extension, the one place formats are declared: a new
#: format is one module plus one line. A double extension (``.compressed.ply``) is matched
#: before the plain one; a key without a leading dot (``meta.json``: a SOG folder) is a whole
#: file name.
FORMATS: dict[str, Format] = {
    ".ply": Format("ply", "ply", chunk_class="PlyChunks"),
    ".compressed.ply": Format("ply", writer="playcanvas", fields=_compressed_ply_fields,
                              **_SPLATS),
    ".splat": Format("splat", fields=lambda path: {"format": ".splat (32-byte records)"},
                     **_SPLATS),
    ".spz": Format("spz", fields=_spz_fields, **_SPLATS),
    ".sog": Format("sog", fields=_sog_fields, **_SPLATS),
    SOG_META: Format("sog", "folder", fields=_sog_fields, **_SPLATS),
    ".glb": Format("gltf", fields=_gltf_fields),
    ".gltf": Format("gltf", fields=_gltf_fields),
    ".pcd": Format("pcd", fields=_pcd_fields),
    ".xyz": Format("open3d_io", "path"),
    ".xyzn": Format("open3d_io", "path"),
    ".pts": Format("open3d_io", "path"),
    ".las": Format("las", "path", chunk_class="LasChunks"),
    ".laz": Format("las", "path", chunk_class="LasChunks"),
}
SUPPORTED = tuple(FORMATS)
#: extensions the streaming / Dask paths read in chunks
STREAMABLE = tuple(ext for ext, fmt in FORMATS.items() if fmt.stream)
#: extensions whose files start with a PLY header (the batch probe reads their counts there)
PLY_EXTENSIONS = tuple(ext for ext in FORMATS if ext.endswith(".ply"))
LAS_EXTENSIONS = tuple(ext for ext, fmt in FORMATS.items() if fmt.module == "las")


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


def load(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    """Load a model file (any extension of :data:`FORMATS`).

    drop_nonfinite: drop vertices with NaN/Inf coordinates (and the faces using them) instead of
    raising. Raises InputError/FormatError with one line naming the file.
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


def save(model: PointModel, path: str | Path, *, text: bool | None = None) -> Path:
    """Save atomically; the format follows the extension (PLY keeps the input's encoding unless
    ``text`` is given). Refuses to overwrite ``model.path``. Returns the written path."""
    path = check_output_path(path, model.path)
    ext = _extension(path, "output")
    from . import las, pcd  # a source of theirs converts when written as another format

    if isinstance(model.source, las.LasSource) and FORMATS[ext].module != "las":
        model = replace(model, source=las.ply_source_from_las(model.source)
                        if ext == ".ply" else None)
    if isinstance(model.source, pcd.PcdSource) and FORMATS[ext].module != "pcd":
        model = replace(model, source=pcd.ply_source_from_pcd(model.source)
                        if ext == ".ply" else None)
    FORMATS[ext].write(model, path, text)
    return path


__all__ = ["FORMATS", "Format", "load", "save", "SUPPORTED", "STREAMABLE", "PLY_EXTENSIONS",
           "LAS_EXTENSIONS", "extension_of", "format_fields", "atomic_path", "atomic_write",
           "check_output_path", "ChunkFile", "open_chunks"]
