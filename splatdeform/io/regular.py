"""Refuse input paths that are not regular files (a FIFO, a device, a socket) before opening
them: reading a FIFO blocks until a writer comes, ``/dev/zero`` never ends."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from ..errors import InputError

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a named pipe (FIFO)"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"))


def check_regular(path: str | Path, mode: int) -> None:
    """Raise InputError naming ``path`` unless ``mode`` (an ``st_mode``) is a regular file."""
    if stat.S_ISREG(mode):
        return
    kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
    raise InputError(f"{path}: is {kind}; expected a regular model file")


def require_regular(path: str | Path) -> None:
    """Stat ``path`` (following links, without opening it) and refuse anything not regular."""
    check_regular(path, os.stat(path).st_mode)
