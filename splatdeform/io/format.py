"""What a format declaration is (:class:`Format`) and what its header probe returns
(:class:`FileCost`): the types the declarations of :mod:`splatdeform.io.declare` fill in and
``splatdeform.io`` merges into one table by extension.

Light on purpose: importing this module (or a declaration) imports no format reader; a
declaration names its reader and writer modules by name, and its probe, ``info`` fields and
source conversion import the format's module only when called.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

from ..errors import SplatdeformError
from .atomic import atomic_path, atomic_write

if TYPE_CHECKING:
    from ..model import PointModel
    from .chunks import ChunkFile

#: enough of a file's first bytes to hold any header the readers accept (PLY: 1 MiB)
HEAD_BYTES = 2**20 + 4096


@dataclass(frozen=True)
class FileCost:
    """What a file holds and what reading it costs, from its validated header and its size.

    points: points the header declares (else a bound from the size); size: file bytes;
    record_bytes: bytes per point once decoded (the model's per-point arrays);
    load_bytes: peak bytes to read the whole file into a PointModel;
    reader_bytes: what a streamed reader holds besides the rows it returns (LAZ: one
    compressed chunk)."""

    points: int
    size: int
    record_bytes: int
    load_bytes: int
    reader_bytes: int = 0


def size_cost(size: int) -> FileCost:
    """The cost of a file whose format declares no header probe (XYZ/PTS text): as many
    12-byte points as the size holds."""
    points = max(size // 12, 1)
    return FileCost(points, size, 24, 4 * size + 48 * points)


#: ``probe(name, head, size, file) -> FileCost``: ``head`` is the file's first
#: :data:`HEAD_BYTES` bytes, ``size`` its size, ``file`` the file itself when there is one
#: (None for an archive member judged before extraction). Raises FormatError/InputError (one
#: line naming ``name``) for a header the reader would refuse.
Probe = Callable[[Path, bytes, int, "Path | None"], FileCost]


@dataclass(frozen=True)
class Format:
    """One file format's declaration.

    ``module``: the module of :mod:`splatdeform.io` that reads it (``read_model(path,
    drop_nonfinite=) -> PointModel``), imported on first use; ``writer``: the writing module
    when another (None: ``module``); ``write_by``: how it is called (``stream``:
    ``write_model(model, path, stream)`` into an atomic stream; ``path``:
    ``write_model(model, tmp_path)``; ``ply``: ``write_model(model, stream, text=)``;
    ``folder``: ``write_folder(model, path)``); ``chunk_class``: the module's ChunkFile class
    for the streaming and Dask paths (None: not streamable); ``probe``: the header probe (the
    validated counts and load cost, :data:`Probe`; None: judged from the size,
    :func:`size_cost`); ``fields``: the format's own fields for ``info`` (None: its header
    shows them); ``convert``: ``convert(model, ext) -> model`` for a model read from this
    format and written as another (its source converted or dropped); ``lidar``: LiDAR scans
    (z-up, elevation colours by default); ``lossy``: a write quantises (and says once what it
    loses)."""

    module: str
    write_by: str = "stream"
    writer: str | None = None
    chunk_class: str | None = None
    probe: Probe | None = None
    fields: Callable[[Path], dict] | None = None
    convert: Callable[[PointModel, str], PointModel] | None = None
    lidar: bool = False
    lossy: bool = False

    @staticmethod
    def _load(name: str) -> ModuleType:
        return importlib.import_module(f"{__package__}.{name}")

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
        """Write ``model`` to ``path`` atomically (``text``: PLY encoding, None: the input's).
        A writer's refusal that names no file is said of ``path`` (the output, never its
        temporary file)."""
        try:
            self._write(model, path, text)
        except SplatdeformError as exc:
            if exc.file is None and str(path) not in str(exc):
                exc.in_file(str(path))
            raise

    def _write(self, model: PointModel, path: Path, text: bool | None) -> None:
        module = self._load(self.writer or self.module)
        if self.write_by == "folder":
            module.write_folder(model, path)
        elif self.write_by == "path":
            with atomic_path(path) as tmp:
                _by_path(module, model, Path(tmp), path)
        else:
            with atomic_write(path) as stream:
                if self.write_by == "ply":
                    module.write_model(model, stream, text=text)
                else:
                    module.write_model(model, path, stream)


def _by_path(module: ModuleType, model: PointModel, tmp: Path, path: Path) -> None:
    """``module.write_model(model, tmp)``, its refusals and warnings said of the output
    ``path`` instead of the temporary file ``tmp`` it writes."""
    def named(text: str) -> str:
        return text.replace(str(tmp), str(path))

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            module.write_model(model, tmp)
        except SplatdeformError as exc:
            exc.message = named(exc.message)
            exc.args = (exc.message,)
            if exc.file is not None:
                exc.file = named(exc.file)
            raise
        finally:
            said = [(named(str(w.message)), w.category) for w in caught]
    for text, category in said:
        warnings.warn(text, category, stacklevel=4)
