"""Atomic output files: write a temporary file in the target folder, then rename it."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from ..errors import InputError


def check_output_path(out: str | Path, *inputs: str | Path | None) -> Path:
    """Validate an output path: not one of ``inputs``, parent folder creatable, not a folder."""
    out = Path(out)
    for inp in inputs:
        if inp is None:
            continue
        inp = Path(inp)
        same = out.resolve() == inp.resolve() or (
            out.exists() and inp.exists() and os.path.samefile(out, inp))
        if same:
            raise InputError(f"{out}: refusing to overwrite the input file; choose another output")
    if out.is_dir():
        raise InputError(f"{out}: is a directory; expected an output file path")
    return out


@contextlib.contextmanager
def atomic_path(out: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``out``; on success rename it to ``out``, else delete it.

    The temporary name keeps ``out``'s suffix (some writers pick the format by extension).
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.stem}.", suffix=f".tmp{out.suffix}")
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o644)
        os.replace(tmp_path, out)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise


@contextlib.contextmanager
def atomic_write(out: str | Path) -> Iterator:
    """Open a binary stream whose contents replace ``out`` atomically when the block succeeds."""
    with atomic_path(out) as tmp, open(tmp, "wb") as stream:
        yield stream
        stream.flush()
        os.fsync(stream.fileno())
