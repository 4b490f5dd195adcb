"""Where scans come from: files, globs, folders (recursive) and .zip/.tar(.gz/.bz2/.xz) archives.

Archive members are listed up front and read one at a time, on the worker that processes them,
into a private temporary folder (never the whole archive unpacked to disk).
"""

from __future__ import annotations

import contextlib
import glob
import os
import shutil
import tarfile
import tempfile
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from ..errors import ConfigError, InputError
from ..io import SUPPORTED

ARCHIVES = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tbz2", ".tar.xz", ".txz")


@dataclass(frozen=True)
class Scan:
    """One input scan: a file, or a ``member`` of the archive ``path``."""

    path: str
    member: str | None = None
    identity: tuple = ()      # (size, mtime/crc) so a changed input invalidates its output

    @property
    def filename(self) -> str:
        return PurePosixPath(self.member).name if self.member else Path(self.path).name

    @property
    def name(self) -> str:
        return f"{Path(self.path).name}:{self.member}" if self.member else self.path

    @property
    def stem(self) -> str:
        return Path(self.filename).stem

    @property
    def suffix(self) -> str:
        return Path(self.filename).suffix.lower()


def is_glob(pattern: str) -> bool:
    return glob.has_magic(pattern)


def glob_base(pattern: str) -> Path:
    """The folder part of a glob before its first wildcard."""
    parts = Path(pattern).parts
    fixed = []
    for part in parts:
        if glob.has_magic(part):
            break
        fixed.append(part)
    return Path(*fixed).resolve() if fixed else Path.cwd()


def is_archive(path: str | Path) -> bool:
    return str(path).lower().endswith(ARCHIVES)


def _supported(name: str) -> bool:
    base = PurePosixPath(name).name
    return not base.startswith(".") and PurePosixPath(name).suffix.lower() in SUPPORTED


def _file_scan(p: Path) -> Scan:
    st = p.stat()
    return Scan(str(p), None, (st.st_size, st.st_mtime_ns))


def archive_members(path: Path) -> list[Scan]:
    """Model files inside an archive, in archive order; InputError for an unreadable archive."""
    try:
        if path.suffix.lower() == ".zip":
            with zipfile.ZipFile(path) as zf:
                return [Scan(str(path), info.filename, (info.file_size, info.CRC))
                        for info in zf.infolist()
                        if not info.is_dir() and _supported(info.filename)]
        with tarfile.open(path) as tf:
            return [Scan(str(path), m.name, (m.size, m.mtime)) for m in tf.getmembers()
                    if m.isfile() and _supported(m.name)]
    except (zipfile.BadZipFile, tarfile.TarError, OSError, EOFError) as exc:
        raise InputError(f"{path}: cannot read the archive: {exc}") from exc


def _expand_path(p: Path, exclude: Path) -> list[Scan]:
    if p.is_dir():
        out = []
        for root, dirs, files in os.walk(p):
            rootp = Path(root)
            dirs[:] = sorted(d for d in dirs if not d.startswith(".")
                             and (rootp / d).resolve() != exclude)
            for f in sorted(files):
                fp = rootp / f
                if _supported(f):
                    out.append(_file_scan(fp))
                elif is_archive(f):
                    out.extend(archive_members(fp))
        return out
    if is_archive(p):
        return archive_members(p)
    if _supported(p.name):
        return [_file_scan(p)]
    return []


def find_scans(patterns: list[str], base: Path, *, exclude: Path, source: str) -> list[Scan]:
    """Expand the ``scans`` entries (relative to ``base``); ConfigError when nothing matched."""
    seen: dict[tuple[str, str | None], Scan] = {}
    for pattern in patterns:
        full = base / pattern
        if is_glob(pattern):
            paths = [Path(p) for p in sorted(glob.glob(str(full), recursive=True))]
        elif full.exists():
            paths = [full]
        else:
            raise ConfigError(f"{source}: scans: {pattern}: no such file or folder")
        for p in paths:
            p = p.resolve()
            if p == exclude or exclude in p.parents:
                continue
            for scan in _expand_path(p, exclude):
                seen.setdefault((scan.path, scan.member), scan)
    if not seen:
        what = patterns if len(patterns) > 1 else patterns[0]
        raise ConfigError(f"{source}: scans: no scans matched {what!r} "
                          f"(expected files ending in {', '.join(SUPPORTED)}, folders or archives)")
    return list(seen.values())


@contextlib.contextmanager
def materialize(scan: Scan) -> Iterator[Path]:
    """A local file path for the scan: the file itself, or one archive member copied (streamed)
    into a private temporary folder that is removed afterwards."""
    if scan.member is None:
        yield Path(scan.path)
        return
    with tempfile.TemporaryDirectory(prefix="splatdeform-batch-") as tmp:
        target = Path(tmp) / scan.filename
        try:
            if scan.path.lower().endswith(".zip"):
                with zipfile.ZipFile(scan.path) as zf, zf.open(scan.member) as src, \
                        open(target, "wb") as dst:
                    shutil.copyfileobj(src, dst, 1 << 20)
            else:
                with tarfile.open(scan.path) as tf:
                    src = tf.extractfile(scan.member)
                    if src is None:
                        raise InputError(f"{scan.name}: not a regular file in the archive")
                    with src, open(target, "wb") as dst:
                        shutil.copyfileobj(src, dst, 1 << 20)
        except (zipfile.BadZipFile, tarfile.TarError, KeyError, EOFError, OSError) as exc:
            raise InputError(f"{scan.name}: cannot read the archive member: {exc}") from exc
        yield target
