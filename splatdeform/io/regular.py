"""The one opener for every file the program reads.

Refuse input paths that are not regular files (a FIFO, a device, a socket) before reading them:
reading a FIFO blocks until a writer comes, ``/dev/zero`` never ends. Files that a model names
(the members of a SOG folder, the buffers and images of a glTF) must also stay inside the
model's folder: a link leaving it is refused, and so is a name with a path in it.

- :func:`open_regular`: open for reading without ever blocking on a FIFO (``O_NONBLOCK`` for
  the open, cleared after ``fstat`` says it is a regular file); ``inside=`` confines the
  resolved path to a folder.
- :func:`member_path`: the path of a file named by a model file, checked to be a plain name in
  the model's folder.
- :func:`read_regular`: the whole file, refused before reading when it is larger than
  ``max_bytes``.
"""

from __future__ import annotations

import fcntl
import os
import stat
from pathlib import Path
from typing import BinaryIO

from ..errors import FormatError, InputError

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a named pipe (FIFO)"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"))


def check_regular(path: str | Path, mode: int, what: str = "model file") -> None:
    """Raise InputError naming ``path`` unless ``mode`` (an ``st_mode``) is a regular file."""
    if stat.S_ISREG(mode):
        return
    kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
    raise InputError(f"{path}: is {kind}; expected a regular {what}")


def require_regular(path: str | Path) -> None:
    """Stat ``path`` (following links, without opening it) and refuse anything not regular."""
    check_regular(path, os.stat(path).st_mode)


def check_inside(path: str | Path, folder: str | Path, what: str = "file") -> Path:
    """Refuse ``path`` when, links followed, it is not inside ``folder`` (links followed too).
    Returns the resolved path."""
    try:
        real = Path(path).resolve(strict=True)
        base = Path(folder).resolve(strict=True)
    except FileNotFoundError:
        raise InputError(f"{path}: {what} does not exist") from None
    except (OSError, RuntimeError) as exc:
        raise InputError(f"{path}: {what} cannot be resolved ({exc.strerror or exc})") from None
    if real != base and base not in real.parents:
        raise InputError(f"{path}: {what} is a link leading out of its folder {base} "
                         f"(to {real}); expected a file inside the folder")
    return real


def member_path(model: str | Path, name: object, what: str = "member") -> Path:
    """The path of a file that ``model`` names (a SOG member, a glTF buffer or image uri):
    ``name`` must be a plain file name (no folder part, no ``..``, no NUL byte), and the file it
    names, links followed, must stay inside ``model``'s folder (``model`` itself when it is a
    folder). Raises FormatError/InputError naming ``model`` and ``what``."""
    model = Path(model)
    folder = model if model.is_dir() else model.parent
    if not isinstance(name, str) or not name or name in (".", "..") or "/" in name \
            or "\\" in name or "\x00" in name:
        raise FormatError(f"{model}: {what} {name!r} is not a plain file name in the model's "
                          "folder")
    path = folder / name
    if os.path.lexists(path):
        check_inside(path, folder, f"{what} of {model}")
    return path


def open_regular(path: str | Path, *, inside: str | Path | None = None,
                 what: str = "model file") -> BinaryIO:
    """Open ``path`` for binary reading, refusing anything that is not a regular file without
    blocking on it (a FIFO is opened non-blocking, then refused); with ``inside``, a path that
    resolves outside that folder is refused first. Raises InputError naming ``path``;
    FileNotFoundError / PermissionError pass through for the callers' own messages."""
    if inside is not None:
        check_inside(path, inside, what)
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        check_regular(path, os.fstat(fd).st_mode, what)
        flags = fcntl.fcntl(fd, fcntl.F_GETFL)
        fcntl.fcntl(fd, fcntl.F_SETFL, flags & ~os.O_NONBLOCK)
    except BaseException:
        os.close(fd)
        raise
    return os.fdopen(fd, "rb")


def read_regular(path: str | Path, *, max_bytes: int | None = None,
                 inside: str | Path | None = None, what: str = "model file") -> bytes:
    """The whole of a regular file (see :func:`open_regular`); refused with one line naming it
    when it holds more than ``max_bytes``, before anything is read."""
    with open_regular(path, inside=inside, what=what) as fh:
        size = os.fstat(fh.fileno()).st_size
        if max_bytes is not None and size > max_bytes:
            raise FormatError(f"{path}: {what} is {size:,} bytes, more than the {max_bytes:,} "
                              "it can hold")
        data = fh.read(size + 1)
    if len(data) != size:
        raise FormatError(f"{path}: {what} changed size while being read")
    return data
