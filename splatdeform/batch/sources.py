"""Where scans come from: files, globs, folders (recursive) and .zip/.tar(.gz/.bz2/.xz) archives.

Archive members are listed up front and read one at a time, on the worker that processes them,
into a private temporary folder (never the whole archive unpacked to disk), found by their
position in the archive (a name can occur twice; only the first is processed). Nothing that is
not a regular file is ever opened (a FIFO named ``scan.ply`` would block the reader for ever):
such a scan is listed with a ``problem`` and reported failed. Reading a scan onto a worker
(extraction into a temporary folder) is :mod:`splatdeform.batch.extract`'s.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import glob
import os
import stat
import tarfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from ..errors import ConfigError, InputError, error_line
from ..io import SUPPORTED, extension_of, split_extension
from ..memory import HEAD_BYTES

#: longest archive problem a report row keeps (errors.error_line's limit)
PROBLEM_CHARS = 300
ARCHIVES = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tbz2", ".tar.xz", ".txz")
#: compressions of a tar whose extension has two parts (``x.tar.gz``)
_TAR_COMPRESSIONS = (".gz", ".bz2", ".xz")


@dataclass(frozen=True)
class Scan:
    """One input scan: a file, or a ``member`` of the archive ``path`` (the ``index``-th entry).

    ``problem`` is set for a scan that is reported failed without being processed (not a regular
    file, a duplicate archive member name). ``occurrence`` > 1 tells apart scans whose names
    would otherwise be equal (it is appended to the name as ``#N``)."""

    path: str
    member: str | None = None
    identity: tuple = ()      # (size, mtime/crc) so a changed input invalidates its output
    index: int | None = None  # position in the archive's listing
    size: int | None = None   # bytes (the archive's declared member size for a member)
    problem: str | None = None
    occurrence: int = 1
    need: int | None = None   # estimated peak bytes to deform it (archive members, from the header)
    offset: int | None = None  # a tar member's header offset (read without listing the archive)

    @property
    def filename(self) -> str:
        return PurePosixPath(self.member).name if self.member else Path(self.path).name

    @property
    def name(self) -> str:
        base = f"{Path(self.path).name}:{self.member}" if self.member else self.path
        return base if self.occurrence == 1 else f"{base}#{self.occurrence}"

    @property
    def stem(self) -> str:
        return Path(self.filename).stem

    @property
    def extension(self) -> str:
        """The format's extension (``.compressed.ply`` for a compressed PLY), by
        :func:`splatdeform.io.extension_of`."""
        return extension_of(self.filename)


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


MAX_GLOB_ENTRIES = 200_000   # folder entries one scans glob may visit
SKIPPED_ROOTS = ("/proc", "/sys", "/dev")


def _match_parts(parts: tuple[str, ...], pat: tuple[str, ...]) -> bool:
    """Glob semantics on path parts: ``**`` matches zero or more folders, other parts match one
    name with fnmatch; names starting with '.' only match a part that starts with '.'."""
    memo: dict[tuple[int, int], bool] = {}

    def go(i: int, j: int) -> bool:
        if (i, j) in memo:
            return memo[i, j]
        if j == len(pat):
            ok = i == len(parts)
        elif pat[j] == "**":
            ok = go(i, j + 1) or (i < len(parts) and not parts[i].startswith(".")
                                  and go(i + 1, j))
        else:
            ok = (i < len(parts) and (not parts[i].startswith(".") or pat[j].startswith("."))
                  and fnmatch.fnmatchcase(parts[i], pat[j]) and go(i + 1, j + 1))
        memo[i, j] = ok
        return ok

    return go(0, 0)


def bounded_glob(pattern: str, source: str) -> list[Path]:
    """Paths matching ``pattern`` (``**`` recursive), sorted. Symlinked folders are followed
    at most once each (a symlink loop is not walked again), /proc, /sys and /dev are never
    entered, and at most :data:`MAX_GLOB_ENTRIES` entries are visited (ConfigError past it)."""
    base = glob_base(pattern)
    pat = _magic_tail(pattern)
    recursive = "**" in pat
    out: list[Path] = []
    seen_dirs: set[tuple[int, int]] = set()
    visited = 0
    for root, dirs, files in os.walk(base, followlinks=True):
        rootp = Path(root)
        rel = rootp.relative_to(base).parts
        try:
            st = rootp.stat()
        except OSError:
            dirs[:] = []
            continue
        if (st.st_dev, st.st_ino) in seen_dirs or str(rootp) in SKIPPED_ROOTS:
            dirs[:] = []
            continue
        seen_dirs.add((st.st_dev, st.st_ino))
        visited += len(dirs) + len(files)
        if visited > MAX_GLOB_ENTRIES:
            raise ConfigError(f"{source}: scans: {pattern}: the pattern visits more than "
                              f"{MAX_GLOB_ENTRIES:,} files and folders; narrow it")
        if not recursive:   # descend only where the pattern has more parts
            dirs[:] = [d for d in dirs if len(rel) + 1 < len(pat)
                       and _match_parts(rel + (d,), pat[:len(rel) + 1])]
        for name in dirs + files:
            if _match_parts(rel + (name,), pat):
                out.append(rootp / name)
    return sorted(set(out))


def _magic_tail(pattern: str) -> tuple[str, ...]:
    parts = Path(pattern).parts
    for i, part in enumerate(parts):
        if glob.has_magic(part):
            return parts[i:]
    return ()


def archive_extension(path: str | Path) -> str:
    """The archive extension of ``path``'s name (one of :data:`ARCHIVES`, lower case; '' when it
    is not an archive's), read by io's one parser: ``X.ZIP`` -> ``.zip``, ``scan.TAR.GZ`` ->
    ``.tar.gz`` (the compression's extension after the tar's)."""
    stem, ext = split_extension(path)
    if ext in _TAR_COMPRESSIONS and extension_of(stem) == ".tar":
        ext = ".tar" + ext
    return ext if ext in ARCHIVES else ""


def is_archive(path: str | Path) -> bool:
    return archive_extension(path) != ""


def _supported(name: str) -> bool:
    base = PurePosixPath(name).name
    ext = extension_of(base)   # a whole-name key (a SOG folder's meta.json) is not a scan file
    return not base.startswith(".") and ext.startswith(".") and ext in SUPPORTED


def file_kind(mode: int) -> str:
    for test, what in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"),
                       (stat.S_ISDIR, "a directory")):
        if test(mode):
            return what
    return "not a regular file"


def not_regular(p: Path) -> str | None:
    """Why ``p`` cannot be read as a scan without blocking (None: a regular file)."""
    try:
        st = p.stat()
    except OSError as exc:
        return f"cannot read it: {exc.strerror or exc}"
    if stat.S_ISREG(st.st_mode):
        return None
    return f"not a regular file ({file_kind(st.st_mode)}); skipped"


def _file_scan(p: Path) -> Scan:
    problem = not_regular(p)
    if problem is not None:
        return Scan(str(p), problem=problem)
    st = p.stat()
    return Scan(str(p), None, (st.st_size, st.st_mtime_ns), size=st.st_size)


def _vet_head(name: str, head: bytes, size: int) -> tuple[str | None, int | None]:
    """A member judged from its header while the archive is listed: (problem, estimated peak
    bytes). Only the header-vs-size check refuses here; the budget is the runner's."""
    from ..errors import SplatdeformError
    from .probe import check, estimate_memory, probe

    try:
        p = probe(name, head, size)
        check(name, p)
    except SplatdeformError as exc:
        return error_line(exc, limit=PROBLEM_CHARS), None
    return None, estimate_memory(p)


def _zip_overlap(infos: list[zipfile.ZipInfo], end: int) -> str | None:
    """Entries whose data overlap another entry (a 'zip bomb' of many entries sharing one
    member) or the central directory: the archive is refused (one sort, linear after it)."""
    spans = sorted((info.header_offset, 30 + info.compress_size, info.filename)
                   for info in infos)
    ends = spans[1:] + [(end, 0, "the central directory")]
    for (at, length, name), nxt in zip(spans, ends, strict=True):
        if at + length > nxt[0]:
            return (f"archive entries overlap ({name!r} at byte {at:,} runs into {nxt[2]!r} at "
                    f"byte {nxt[0]:,}); refusing the archive")
    return None


def archive_members(path: Path) -> list[Scan]:
    """Model files inside an archive, in archive order, each checked from its header (read
    once, in one pass over the archive: linear in the member count).

    Never raises for the archive's content: a member that cannot be used (a duplicate name,
    a link or special file, a header that does not fit its size) is listed with a ``problem``,
    and an archive that cannot be read (or read to its end: a cut tar header, overlapping zip
    entries) adds one row for the archive itself with the reason."""
    problem = not_regular(path)
    if problem is not None:
        return [Scan(str(path), problem=problem)]
    out: list[Scan] = []
    seen: dict[str, int] = {}

    def add(name: str, index: int, identity: tuple, size: int, regular: bool,
            read_head: Callable[[], bytes], offset: int | None = None) -> None:
        seen[name] = seen.get(name, 0) + 1
        why, need = None, None
        if seen[name] > 1:
            why = (f"duplicate member name in the archive (entry {seen[name]} with this name); "
                   "only the first entry is processed, rename the others")
        elif not regular:
            why = "not a regular file in the archive (a link or special file); skipped"
        else:
            label = f"{path.name}:{name}"
            try:
                head = read_head()
            except Exception as exc:  # noqa: BLE001 - any decoder error is this member's row
                why = (f"{label}: cannot read the archive member: "
                       f"{error_line(exc, limit=PROBLEM_CHARS)}")
            else:
                why, need = _vet_head(label, head, size)
        out.append(Scan(str(path), name, identity, index, size, why, need=need, offset=offset))

    try:
        if extension_of(path) == ".zip":
            _list_zip(path, add)
        else:
            _list_tar(path, add)
    except Exception as exc:  # noqa: BLE001 - zlib/lzma/bz2/struct errors too: a row, not a crash
        why = f"cannot read the archive: {error_line(exc, limit=PROBLEM_CHARS)}"
        out.append(Scan(str(path), problem=why))
    return out


def _list_zip(path: Path, add: Callable[..., None]) -> None:
    with zipfile.ZipFile(path) as zf:
        infos = zf.infolist()
        overlap = _zip_overlap(infos, zf.start_dir)
        if overlap is not None:
            raise InputError(overlap)
        for i, info in enumerate(infos):
            if info.is_dir() or not _supported(info.filename):
                continue

            def head(info: zipfile.ZipInfo = info) -> bytes:
                with zf.open(info) as src:
                    return _read_head(src, min(HEAD_BYTES, info.file_size))

            add(info.filename, i, (info.file_size, info.CRC), info.file_size, True, head)


def _list_tar(path: Path, add: Callable[..., None]) -> None:
    """One pass (a compressed tar is decompressed once); a header that cannot be read after
    the first member is not the end of the archive: it is reported (tarfile would stop
    silently and the members after it would be missing without a word)."""
    with tarfile.open(path) as tf:
        i = 0
        while True:
            m = tf.next()
            if m is None:
                break
            if not m.isdir() and _supported(m.name):
                def head(m: tarfile.TarInfo = m) -> bytes:
                    src = tf.extractfile(m)
                    assert src is not None
                    return _read_head(src, min(HEAD_BYTES, m.size))

                add(m.name, i, (m.size, m.mtime), m.size, m.isfile(), head, m.offset)
            i += 1
        assert tf.fileobj is not None
        tf.fileobj.seek(tf.offset)
        block = tf.fileobj.read(tarfile.BLOCKSIZE)
        if block.strip(b"\0"):
            raise InputError(f"the member header at byte {tf.offset:,} is cut off or unreadable "
                             f"(after {i} entries); the members after it are not listed")


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
    """Expand the ``scans`` entries (relative to ``base``); ConfigError when nothing matched.

    Scans whose names coincide (duplicate archive members, equally named archives in two
    folders) get ``occurrence`` 2, 3, ... so every report row has its own name."""
    seen: dict[tuple[str, str | None, int | None], Scan] = {}
    for pattern in patterns:
        full = base / pattern
        if is_glob(pattern):
            paths = bounded_glob(str(full), source)
        elif full.exists() or full.is_symlink():
            paths = [full]
        else:
            raise ConfigError(f"{source}: scans: {pattern}: no such file or folder")
        for p in paths:
            p = p.resolve()
            if p == exclude or exclude in p.parents:
                continue
            for scan in _expand_path(p, exclude):
                seen.setdefault((scan.path, scan.member, scan.index), scan)
    if not seen:
        what = patterns if len(patterns) > 1 else patterns[0]
        raise ConfigError(f"{source}: scans: no scans matched {what!r} "
                          f"(expected files ending in {', '.join(SUPPORTED)}, folders or archives)")
    out, names = [], {}
    for scan in seen.values():
        n = names[scan.name] = names.get(scan.name, 0) + 1
        out.append(scan if n == 1 else dataclasses.replace(scan, occurrence=n))
    return out


def _read_head(src: BinaryIO, n: int) -> bytes:
    chunks, left = [], n
    while left > 0:
        chunk = src.read(left)
        if not chunk:
            break
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)
