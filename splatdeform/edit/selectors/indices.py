"""``{indices: [i, ...]}`` or ``{indices: {file: path}}``: explicit point indices (a text file of
whitespace-separated integers, or a .npy integer array; relative to the config's folder)."""

from __future__ import annotations

import io
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from splatdeform.edit.schema import Index, Strict
from splatdeform.edit.units import Frame, check_units
from splatdeform.errors import InputError
from splatdeform.io import extension_of
from splatdeform.model import PointModel

NAME = "indices"
MAX_LITERAL_INDICES = 100_000  # longer selections belong in a file (indices: {file: ...})
MAX_FILE_BYTES = 256 * 2**20  # an indices file (text or .npy)


@dataclass(frozen=True)
class Indices:
    """Explicit point indices, or a file of them (whitespace separated text, or .npy).

    Parameters
    ----------
    indices : tuple of int
        Point indices in 0..N-1 (used when ``file`` is None).
    file : str, optional
        A text file of whitespace-separated integers or a ``.npy`` integer array; a relative
        path starts at ``base_dir`` (an edit config's folder).

    Examples
    --------
    >>> import numpy as np
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)
    >>> np.flatnonzero(sd.Indices(indices=(5, 0, 7)).mask(bar))
    array([0, 5, 7])
    >>> np.save("picked.npy", np.arange(100, 110))
    >>> int(sd.select(bar, [sd.Indices(file="picked.npy")], base_dir=None).sum())
    10
    >>> sd.Indices(indices=(3000,)).mask(bar)
    Traceback (most recent call last):
    ...
    splatdeform.errors.InputError: indices: expected values in 0..1999, got 3000..3000
    """

    indices: tuple[int, ...] = ()
    file: str | None = None

    def load(self, base_dir: Path | None = None) -> np.ndarray:
        """(M,) int64 indices as given (not yet range-checked)."""
        return load_indices(self, base_dir)

    def mask(self, model: PointModel, base_dir: Path | None = None) -> np.ndarray:
        """(N,) bool."""
        return index_mask(self.load(base_dir), model.n_points)

    def in_units(self, units: str, frame: Frame) -> Indices:
        check_units(units)
        return self

    def to_config(self, base_dir: Path | None = None) -> dict:
        """An indices file becomes absolute against ``base_dir`` (the YAML may move)."""
        if self.file is None:
            return {NAME: [int(i) for i in self.indices]}
        path = Path(self.file)
        if base_dir is not None and not path.is_absolute():
            path = (base_dir / path).resolve()
        return {NAME: {"file": str(path)}}


def index_mask(idx: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool with ``idx`` set; InputError for indices outside 0..n-1."""
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise InputError(f"indices: expected values in 0..{n - 1}, got "
                         f"{int(idx.min())}..{int(idx.max())}")
    mask = np.zeros(n, dtype=bool)
    mask[idx] = True
    return mask


def load_indices(sel: Indices, base_dir: Path | None) -> np.ndarray:
    if sel.file is None:
        try:
            return np.asarray(sel.indices, dtype=np.int64)
        except OverflowError:
            raise InputError("indices: expected point indices below 2**63") from None
    path = Path(sel.file)
    if base_dir is not None and not path.is_absolute():
        path = base_dir / path
    raw = _read_indices_file(path)
    try:
        if extension_of(path) == ".npy":   # io's one parser: P.NPY is a .npy array too
            arr = np.load(io.BytesIO(raw), allow_pickle=False)
            if arr.dtype.kind not in "iu":
                raise ValueError(f"expected an integer array, got dtype {arr.dtype}")
            if arr.size and arr.dtype.kind == "u" and arr.max() > np.iinfo(np.int64).max:
                raise OverflowError("index too large")
            return arr.astype(np.int64).ravel()
        try:
            text = raw.decode("utf-8-sig")
        except UnicodeDecodeError:
            raise ValueError("not UTF-8 text (a .npy array needs the .npy extension)") from None
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # "input contained no data" becomes the error below
            return np.loadtxt(io.StringIO(text), dtype=np.int64, ndmin=1).ravel()
    except UserWarning:
        raise InputError(f"{path}: holds no indices (only blanks or comments); expected integer "
                         "point indices") from None
    except (ValueError, OverflowError, EOFError) as exc:
        raise InputError(f"{path}: expected integer point indices: {_short(exc)}") from None


def _short(exc: BaseException) -> str:
    """The first line of ``exc``, at most 120 characters: never a file's contents at length."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return text if len(text) <= 120 else text[:117] + "..."


def _read_indices_file(path: Path) -> bytes:
    """The bytes of an indices file through the one opener (a regular file of at most
    MAX_FILE_BYTES); InputError naming it otherwise."""
    from splatdeform.errors import FormatError
    from splatdeform.io.regular import read_regular

    try:
        raw = read_regular(path, max_bytes=MAX_FILE_BYTES, what="indices file")
    except FileNotFoundError:
        raise InputError(f"{path}: indices file not found") from None
    except FormatError as exc:
        raise InputError(str(exc)) from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the indices file ({exc.strerror or exc})") from None
    if not raw:
        raise InputError(f"{path}: the indices file is empty; expected integer point indices")
    return raw


class Entry(Strict):
    indices: list[Index] | dict[Literal["file"], str] = Field(
        description="Point indices [i, ...] (at most 100,000), or {file: path}: a text file of "
        "integers or a .npy integer array, relative to the config file")

    @field_validator("indices", mode="before")
    @classmethod
    def _not_too_many(cls, value):
        if isinstance(value, list) and len(value) > MAX_LITERAL_INDICES:
            raise ValueError(f"{len(value):,} literal indices, more than "
                             f"{MAX_LITERAL_INDICES:,}; put them in a file and write "
                             "indices: {file: picked.txt} (or a .npy)")
        return value

    def to_selector(self) -> Indices:
        if isinstance(self.indices, dict):
            return Indices(file=self.indices["file"])
        return Indices(indices=tuple(self.indices))
