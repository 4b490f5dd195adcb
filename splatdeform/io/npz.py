"""The one bounded reader of ``.npz`` files the program did not write in this run (a saved
field, ``splatdeform apply``): an ``.npz`` is a zip of ``.npy`` members, and every size in it is
declared before the data.

:func:`read_npz` checks, before inflating anything:

1. the end of the zip (its last record): at most ``max_members`` entries and a central
   directory of at most :data:`MAX_DIRECTORY_BYTES` (a directory of millions of entries would
   cost gigabytes of Python objects before any member is read);
2. the directory: each member's name (``NAME.npy``, NAME accepted by the caller), its method
   (stored or deflated), the sum of the declared sizes (at most ``max_expansion`` times the
   file plus :data:`EXTRA_BYTES`: a 1 MB member that inflates to 1 GiB is refused by what it
   declares, and the zip reader never inflates past the declared size);
3. each member's ``.npy`` header (dtype, shape, order) through the caller's ``header`` check
   (no object dtype: pickles are never loaded), and that the header's shape times the item
   size is the declared size;

then reads each member's bytes into an array of that dtype and shape. Every refusal is one
:class:`~splatdeform.errors.FormatError` line ``LABEL: member 'NAME': what``.
"""

from __future__ import annotations

import os
import re
import struct
import zipfile
import zlib
from collections.abc import Callable, Collection
from pathlib import Path

import numpy as np

from ..errors import FormatError
from .regular import open_regular

MAX_DIRECTORY_BYTES = 1 << 20  # a central directory (about 100 bytes per member)
EXTRA_BYTES = 1 << 20  # declared sizes beyond max_expansion x the file
MAX_HEADER_BYTES = 10_000  # an .npy header (numpy's own default limit)
READ_BLOCK = 1 << 20
_EOCD = b"PK\x05\x06"
_NAME = re.compile(r"^([A-Za-z_][A-Za-z0-9_]{0,63})\.npy$")

HeaderCheck = Callable[[str, tuple, np.dtype], None]


def _end_record(fh, size: int, label: str) -> tuple[int, int]:
    """(entries, directory bytes) from the zip's end-of-central-directory record."""
    tail_len = min(size, 22 + 0xFFFF)
    fh.seek(size - tail_len)
    tail = fh.read(tail_len)
    at = tail.rfind(_EOCD)
    if at < 0 or len(tail) - at < 22:
        raise FormatError(f"{label}: not an .npz file (no zip directory at its end)")
    (_sig, _disk, _cd_disk, _here, entries, cd_size, _cd_off,
     _comment) = struct.unpack("<4s4H2LH", tail[at:at + 22])
    return entries, cd_size


def _member_name(info: zipfile.ZipInfo, label: str, allowed: Callable[[str], bool]) -> str:
    m = _NAME.match(info.filename)
    if m is None:
        raise FormatError(f"{label}: member {info.filename[:80]!r}: not an .npy member name")
    name = m.group(1)
    if not allowed(name):
        raise FormatError(f"{label}: member {name!r}: not a member of this file")
    if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        raise FormatError(f"{label}: member {name!r}: compression method {info.compress_type} "
                          "(expected stored or deflated)")
    return name


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, name: str, label: str,
                 header: HeaderCheck) -> np.ndarray:
    fmt = np.lib.format
    where = f"{label}: member {name!r}"
    with zf.open(info) as f:
        try:
            version = fmt.read_magic(f)
            if version == (1, 0):
                shape, fortran, dtype = fmt.read_array_header_1_0(
                    f, max_header_size=MAX_HEADER_BYTES)
            elif version in ((2, 0), (3, 0)):
                shape, fortran, dtype = fmt.read_array_header_2_0(
                    f, max_header_size=MAX_HEADER_BYTES)
            else:
                raise ValueError(f"npy version {version}")
        except (ValueError, SyntaxError, TypeError, EOFError, struct.error) as exc:
            raise FormatError(f"{where}: not an .npy array "
                              f"({' '.join(str(exc).split())[:80]})") from None
        if dtype.hasobject or dtype.kind == "V":
            raise FormatError(f"{where}: expected a numeric array, got dtype {dtype} "
                              "(objects and records are never read)")
        header(name, tuple(int(s) for s in shape), dtype)
        count = int(np.prod(shape, dtype=np.int64)) if len(shape) else 1
        nbytes = count * dtype.itemsize
        if f.tell() + nbytes != info.file_size:
            raise FormatError(f"{where}: its header declares {nbytes:,} bytes of data, the "
                              f"archive {info.file_size - f.tell():,}")
        data = bytearray(nbytes)  # filled a block at a time: no second copy of the member
        view, pos = memoryview(data), 0
        while pos < nbytes:
            block = f.read(min(READ_BLOCK, nbytes - pos))
            if not block:
                break
            view[pos:pos + len(block)] = block
            pos += len(block)
    if pos != nbytes:
        raise FormatError(f"{where}: truncated ({pos:,} of {nbytes:,} bytes)")
    array = np.frombuffer(data, dtype=dtype, count=count)
    if fortran:
        return np.ascontiguousarray(array.reshape(shape, order="F"))
    return array.reshape(shape)


def read_npz(path: str | Path, *, label: str, max_bytes: int, max_members: int,
             allowed: Callable[[str], bool], header: HeaderCheck,
             max_expansion: float = 4.0, extra_bytes: int = EXTRA_BYTES,
             what: str = "file", names: Collection[str] | None = None
             ) -> dict[str, np.ndarray]:
    """The members of the ``.npz`` at ``path`` as arrays (name without ``.npy`` -> array),
    each checked as the module says before it is read; ``label`` starts every error line
    (``"field F.npz"``). ``allowed(name)``: whether a member of that name may be there;
    ``header(name, shape, dtype)`` raises for a member it refuses (before its data is read);
    the declared sizes may sum to ``max_expansion`` x the file + ``extra_bytes``; ``names``:
    read only these members (the others' directory entries are still checked)."""
    path = Path(path)
    try:
        fh = open_regular(path, what=what)
    except FileNotFoundError:
        raise FormatError(f"{label}: no such file") from None
    with fh:
        size = os.fstat(fh.fileno()).st_size
        if size > max_bytes:
            raise FormatError(f"{label}: {size:,} bytes, more than the {max_bytes:,} a {what} "
                              "can hold")
        entries, cd_size = _end_record(fh, size, label)
        if entries > max_members or cd_size > MAX_DIRECTORY_BYTES:
            raise FormatError(f"{label}: its zip directory declares {entries:,} members in "
                              f"{cd_size:,} bytes; a {what} has at most {max_members}")
        fh.seek(0)
        try:
            zf = zipfile.ZipFile(fh)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, ValueError,
                NotImplementedError) as exc:
            raise FormatError(f"{label}: not an .npz file "
                              f"({' '.join(str(exc).split())[:80]})") from None
        with zf:
            infos = zf.infolist()
            if len(infos) > max_members:
                raise FormatError(f"{label}: {len(infos)} members; a {what} has at most "
                                  f"{max_members}")
            members = [_member_name(info, label, allowed) for info in infos]
            if len(set(members)) != len(members):
                dup = next(n for n in members if members.count(n) > 1)
                raise FormatError(f"{label}: member {dup!r}: stored twice")
            declared = sum(max(info.file_size, 0) for info in infos)
            limit = int(max_expansion * size) + extra_bytes
            if declared > limit:
                big = max(infos, key=lambda i: i.file_size)
                raise FormatError(f"{label}: member {members[infos.index(big)]!r}: declares "
                                  f"{big.file_size:,} bytes; the members of a {size:,}-byte "
                                  f"{what} may declare at most {limit:,}")
            out = {}
            for info, name in zip(infos, members, strict=True):
                if names is not None and name not in names:
                    continue
                try:
                    out[name] = _read_member(zf, info, name, label, header)
                except FormatError:
                    raise
                except (zipfile.BadZipFile, EOFError, OSError, zipfile.LargeZipFile, zlib.error,
                        ValueError, RuntimeError, NotImplementedError, struct.error) as exc:
                    if isinstance(exc, OSError) and exc.errno is not None:
                        raise  # the disk, not the file: the CLI's own line
                    raise FormatError(f"{label}: member {name!r}: unreadable "
                                      f"({' '.join(str(exc).split())[:80]})") from None
            return out
