"""Archive members and scan files read onto a worker: each member extracted into a private
temporary folder (never the whole archive unpacked), capped at the size the archive declares,
never past the disk's free space; folders named by their owner's pid and host, so folders of
processes that are gone (killed mid-extraction) are removed by :func:`clean_stale_temps` at the
start and end of each batch and of each scan. Files go through the one opener (never blocks on a
FIFO)."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import socket
import stat
import tarfile
import tempfile
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

from ..errors import InputError
from ..io import extension_of
from ..io.atomic import pid_alive
from ..io.regular import open_regular
from ..memory import HEAD_BYTES
from .sources import Scan, _read_head

# -- temporary folders for archive members -----------------------------------------------------

TEMP_PREFIX = "splatdeform-batch-"


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9.]", "_", socket.gethostname())[:64] or "host"


def temp_prefix() -> str:
    """``splatdeform-batch-<pid>-<host>-``: who owns a temporary folder, for stale cleanup."""
    return f"{TEMP_PREFIX}{os.getpid()}-{_host()}-"


def clean_stale_temps(tmpdir: str | None = None) -> list[str]:
    """Remove this tool's temporary folders left by killed processes: only folders named by
    :func:`temp_prefix`, owned by this user, made on this host, whose process is gone.
    Returns the removed paths."""
    tmpdir = tmpdir or tempfile.gettempdir()
    host, me, removed = _host(), os.getpid(), []
    try:
        entries = list(os.scandir(tmpdir))
    except OSError:
        return removed
    for entry in entries:
        if not entry.name.startswith(TEMP_PREFIX):
            continue
        parts = entry.name[len(TEMP_PREFIX):].split("-")
        if len(parts) != 3 or not parts[0].isdigit() or parts[1] != host:
            continue
        try:
            st = entry.stat(follow_symlinks=False)
        except OSError:
            continue
        pid = int(parts[0])
        if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or pid == me or pid_alive(pid):
            continue
        shutil.rmtree(entry.path, ignore_errors=True)
        removed.append(entry.path)
    return removed


Vet = Callable[[bytes, int], None]


@contextlib.contextmanager
def _open_member(scan: Scan) -> Iterator[BinaryIO]:
    """The member's byte stream, found by its position (names can repeat in an archive)."""
    changed = InputError(f"{scan.name}: the archive changed since it was listed; run again")
    if extension_of(scan.path) == ".zip":
        with zipfile.ZipFile(scan.path) as zf:
            infos = zf.infolist()
            if scan.index is None or scan.index >= len(infos) or \
                    infos[scan.index].filename != scan.member:
                raise changed
            with zf.open(infos[scan.index]) as src:
                yield src
        return
    with tarfile.open(scan.path) as tf:
        if scan.offset is None:
            raise changed
        assert tf.fileobj is not None
        tf.fileobj.seek(scan.offset)
        try:
            member = tarfile.TarInfo.fromtarfile(tf)
        except tarfile.HeaderError:
            raise changed from None
        if member.name != scan.member:
            raise changed
        src = tf.extractfile(member)
        if src is None:
            raise InputError(f"{scan.name}: not a regular file in the archive")
        with src:
            yield src


def _open_regular(path: Path) -> BinaryIO:
    """Open for reading through the one opener (never blocks on a FIFO); InputError for a
    non-regular or unreadable file."""
    try:
        return open_regular(path)
    except OSError as exc:
        raise InputError(f"{path}: cannot read it: {exc.strerror or exc}") from exc


def _copy_capped(src: BinaryIO, dst: BinaryIO, head: bytes, size: int, name: str) -> None:
    dst.write(head)
    written = len(head)
    while True:
        chunk = src.read(1 << 20)
        if not chunk:
            break
        written += len(chunk)
        if written > size:
            raise InputError(f"{name}: the member holds more than the {size:,} bytes the archive "
                             "declares; refusing to extract it")
        dst.write(chunk)


@contextlib.contextmanager
def materialize(scan: Scan, vet: Vet | None = None) -> Iterator[Path]:
    """A local file path for the scan: the file itself, or one archive member copied (streamed)
    into a private temporary folder that is removed afterwards.

    ``vet(head, size)`` sees the first bytes (up to ``probe.HEAD_BYTES``) and the size before
    anything is extracted, and raises to refuse the scan. A member is never extracted past the
    size the archive declares for it, nor into a temp folder without room for it."""
    if scan.member is None:
        path = Path(scan.path)
        with _open_regular(path) as f:
            size = os.fstat(f.fileno()).st_size
            if vet is not None:
                vet(_read_head(f, HEAD_BYTES), size)
        yield path
        return
    tmp = tempfile.mkdtemp(prefix=temp_prefix())
    try:
        target = Path(tmp) / scan.filename
        try:
            with _open_member(scan) as src:
                size = scan.size if scan.size is not None else 0
                head = _read_head(src, min(HEAD_BYTES, size + 1))
                if len(head) > size:
                    raise InputError(f"{scan.name}: the member holds more than the {size:,} "
                                     "bytes the archive declares; refusing to extract it")
                if vet is not None:
                    vet(head, size)
                free = shutil.disk_usage(tmp).free
                if size > free:
                    raise InputError(f"{scan.name}: extracting it needs {size / 2**20:.0f} MiB "
                                     f"in {Path(tmp).parent}, only {free / 2**20:.0f} MiB free")
                with open(target, "wb") as dst:
                    _copy_capped(src, dst, head, size, scan.name)
        except (zipfile.BadZipFile, tarfile.TarError, KeyError, EOFError, OSError,
                RuntimeError) as exc:
            raise InputError(f"{scan.name}: cannot read the archive member: {exc}") from exc
        yield target
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
