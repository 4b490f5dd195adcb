"""Loading and saving models, dispatched by file extension.

``load(path)`` never returns an empty model: it raises an :class:`~splatdeform.errors.InputError`
naming the file. ``save(model, path)`` writes atomically and refuses to overwrite the file the
model was loaded from.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from ..errors import FormatError, InputError
from ..model import PointModel
from . import las, open3d_io, ply
from .atomic import atomic_path, atomic_write, check_output_path
from .regular import require_regular


@dataclass(frozen=True)
class Format:
    """One file format: ``read(path, drop_nonfinite=) -> PointModel`` and
    ``write(model, path, text)`` (atomic)."""

    read: Callable[..., PointModel]
    write: Callable[[PointModel, Path, bool | None], None]


def _write_ply(model: PointModel, path: Path, text: bool | None) -> None:
    with atomic_write(path) as stream:
        ply.write_model(model, stream, text=text)


def _write_las(model: PointModel, path: Path, text: bool | None) -> None:
    with atomic_path(path) as tmp:
        las.write_model(model, tmp)


def _write_open3d(model: PointModel, path: Path, text: bool | None) -> None:
    with atomic_path(path) as tmp:
        open3d_io.write_model(model, tmp)


#: Readers and writers in one table by extension: a new format is one module plus one line.
FORMATS: dict[str, Format] = {
    ".ply": Format(ply.read_model, _write_ply),
    **{ext: Format(open3d_io.read_model, _write_open3d) for ext in open3d_io.EXTENSIONS},
    **{ext: Format(las.read_model, _write_las) for ext in las.EXTENSIONS},
}
READERS = {ext: fmt.read for ext, fmt in FORMATS.items()}
SUPPORTED = tuple(FORMATS)


def _extension(path: Path, what: str) -> str:
    ext = path.suffix.lower()
    if ext not in READERS:
        raise InputError(f"{path}: unknown {what} extension {ext or '(none)'!r}; expected one of "
                         f"{', '.join(SUPPORTED)}")
    return ext


def load(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    """Load a model file (.ply, .las, .laz, .pcd, .xyz, .xyzn, .pts).

    drop_nonfinite: drop vertices with NaN/Inf coordinates (and the faces using them) instead of
    raising. Raises InputError/FormatError with one line naming the file.
    """
    path = Path(path)
    if not path.exists():
        if path.is_symlink():
            raise InputError(f"{path}: is a symbolic link to nothing (dangling, or a loop); "
                             "expected a model file")
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a directory; expected a model file")
    require_regular(path)  # a FIFO or a device would block or never end
    ext = _extension(path, "model file")
    try:
        return READERS[ext](path, drop_nonfinite=drop_nonfinite)
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
    if isinstance(model.source, las.LasSource) and ext not in las.EXTENSIONS:
        model = replace(model, source=las.ply_source_from_las(model.source)
                        if ext == ".ply" else None)
    FORMATS[ext].write(model, path, text)
    return path


__all__ = ["FORMATS", "Format", "load", "save", "SUPPORTED", "atomic_path", "atomic_write",
           "check_output_path"]
