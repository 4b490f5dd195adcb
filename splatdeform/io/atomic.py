"""Every output the tool writes goes through here.

- :func:`check_io_paths` is the one check, run before any work starts, that no output is an input
  or another output (same file by ``os.path.samefile`` when both exist, by resolved path
  otherwise) and that no output is an existing non-regular file (folder, FIFO, device node).
- :func:`atomic_path` / :func:`atomic_write`: write a temporary file in the target folder
  (``.NAME.<pid>-<random>.tmp.EXT``), then rename it over the target with the mode a normal
  write would leave (an existing file keeps its mode, a new one gets 0666 less the umask), for
  models, images, GIFs, reports, caches and camera files alike. Temporary files of this tool
  for the same target whose writer is gone (killed) are removed first: only names of exactly
  that pattern (a pid that is not running and tempfile's random part), never a link.
- An output that is a symbolic link is written where it points (the link stays); a dangling
  link is refused, never replaced.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from ..errors import InputError
from ..interrupts import deferred_signals

PathLike = str | os.PathLike
Named = tuple[str, PathLike | None]  # (what it is, e.g. "input model", path)


def _check_chars(what: str, path: PathLike) -> None:
    if "\x00" in os.fspath(path):
        raise InputError(f"{what} {os.fspath(path)!r}: a path must not contain a NUL byte")


def _stat(path: Path) -> os.stat_result | None:
    try:
        return path.stat()
    except FileNotFoundError:
        return None
    except OSError as exc:
        if exc.errno in (errno.ENOTDIR, errno.ENAMETOOLONG, errno.ELOOP):
            return None  # cannot exist; creating it will fail with its own clear error
        raise


def _resolve(path: Path) -> Path:
    try:
        return path.resolve()
    except (RuntimeError, OSError):  # a symlink loop (RuntimeError before Python 3.13)
        raise InputError(f"{path}: is a symbolic link loop; expected a file path") from None


def _same(a: Path, b: Path) -> bool:
    sa, sb = _stat(a), _stat(b)
    if sa is not None and sb is not None:
        return (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino)
    return _resolve(a) == _resolve(b)


NAME_MAX = 255
TEMP_EXTRA = 32  # ".", ".<pid>-<random>.tmp" around the name of the temporary file


def _check_target(what: str, out: Path) -> None:
    """The output's name fits (with its temporary name) and its folder exists or can be made."""
    for part in out.parts:
        if len(os.fsencode(part)) > NAME_MAX:
            raise InputError(f"{what} {out}: a path component is longer than {NAME_MAX} bytes "
                             "(name too long)")
    if len(os.fsencode(out.name)) + TEMP_EXTRA > NAME_MAX:
        raise InputError(f"{what} {out}: file name too long (at most "
                         f"{NAME_MAX - TEMP_EXTRA} bytes, the temporary file beside it needs "
                         "the rest)")
    folder = out.parent
    while _stat(folder) is None and folder != folder.parent:
        folder = folder.parent
    st = _stat(folder)
    if st is not None and not stat.S_ISDIR(st.st_mode):
        raise InputError(f"{what} {out}: cannot create its folder, {folder} is not a directory")
    if st is not None and not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"{what} {out}: folder {folder} is not writable (read-only or "
                         "permission denied)")


def check_io_paths(inputs: Iterable[Named], outputs: Iterable[Named]) -> None:
    """Refuse, before any work, outputs that would destroy an input or another output.

    inputs / outputs: (label, path) pairs, path None to skip; labels name the argument or config
    key (``"--render"``, ``"output"``, ``"input model"``). Raises InputError when an output is the
    same file as an input or as another output, or exists and is not a regular file; a NUL byte
    in any path is refused too.
    """
    ins = [(w, Path(p)) for w, p in inputs if p is not None]
    outs = [(w, Path(p)) for w, p in outputs if p is not None]
    for what, p in ins + outs:
        _check_chars(what, p)
    for i, (what, out) in enumerate(outs):
        if out.is_symlink() and _stat(out) is None:
            raise InputError(f"{what} {out}: is a symbolic link to nothing (dangling, or a "
                             "loop); refusing to replace the link, give the path to write")
        st = _stat(out)
        if st is not None and not stat.S_ISREG(st.st_mode):
            kind = ("a directory" if stat.S_ISDIR(st.st_mode) else
                    "a FIFO" if stat.S_ISFIFO(st.st_mode) else
                    "a device node" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else
                    "not a regular file")
            raise InputError(f"{what} {out}: exists and is {kind}; expected a regular file path "
                             "to write")
        _check_target(what, out)
        for in_what, inp in ins:
            if _same(out, inp):
                raise InputError(f"{what} {out}: is the {in_what} ({inp}); refusing to overwrite "
                                 "an input, choose another output path")
        for other_what, other in outs[:i]:
            if _same(out, other):
                raise InputError(f"{what} {out}: is also the {other_what} output; choose "
                                 "different output paths")


def check_output_path(out: PathLike, *inputs: PathLike | None) -> Path:
    """Validate one output path against ``inputs`` (see :func:`check_io_paths`)."""
    check_io_paths([("input file", p) for p in inputs], [("output", out)])
    return Path(out)


# ------------------------------------------------------------------------ temporary files

RANDOM_CHARS = "a-z0-9_"  # tempfile's alphabet and length for the random part of a name
RANDOM_LEN = 8


# ``.STEM.<pid>-<random>.tmp.EXT``: exactly what :func:`atomic_path` creates (a pid and
# tempfile's 8-character random part), so a user's file that merely looks temporary
# (``.keep.abcdef12.tmp.ply``, ``.notes.tmp``, ``.report.json.123-abcd.tmp.json``) never matches.
_TEMP_NAME = re.compile(rf"^\.(?P<stem>.+)\.(?P<pid>[1-9]\d{{0,9}})-[{RANDOM_CHARS}]"
                        rf"{{{RANDOM_LEN}}}\.tmp(?P<suffix>\.[^.]+)?$")


def temp_owner(name: str, out: Path | None = None) -> int | None:
    """The pid in ``name`` when it is exactly a temporary name :func:`atomic_path` makes (for
    the output ``out`` when given, else for any output in its folder); None otherwise."""
    m = _TEMP_NAME.match(name)
    if m is None:
        return None
    if out is not None and (m["stem"] != out.stem or (m["suffix"] or "") != out.suffix):
        return None
    return int(m["pid"])


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists on this machine (another user's counts as alive, so its
    files are kept; a number no process can have is gone)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (OverflowError, ValueError):
        return False
    except OSError:   # EPERM: another user's live process
        return True
    return True


def _remove_dead(folder: Path, names: Iterable[str], out: Path | None) -> list[Path]:
    removed = []
    for name in names:
        pid = temp_owner(name, out)
        if pid is None or pid_alive(pid):
            continue
        p = folder / name
        with contextlib.suppress(OSError):
            if stat.S_ISREG(os.lstat(p).st_mode):
                p.unlink()
                removed.append(p)
    return removed


def remove_stale_temps(out: PathLike, *, any_output: bool = False) -> list[Path]:
    """The one stale-temporary cleaner: remove this tool's temporary files beside ``out`` left
    by a killed writer, i.e. files named exactly as :func:`atomic_path` names them whose pid is
    not running. Never a link, never anything else. ``any_output``: ``out`` is a folder, and
    the temporaries of every output in it are candidates (a batch's ``output_dir``).
    Returns the removed paths; never raises."""
    out = Path(out)
    folder = out if any_output else out.parent
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    if any_output:
        return _remove_dead(folder, names, None)
    prefix, suffix = f".{out.stem}.", f".tmp{out.suffix}"
    # cheap filter first: output folders of a batch hold many files
    return _remove_dead(folder, [n for n in names if n.startswith(prefix) and n.endswith(suffix)],
                        out)


def current_umask() -> int:
    """The process umask, read without changing it where Linux tells it (/proc)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)  # elsewhere: read it by setting it (not thread-safe, rare)
    os.umask(mask)
    return mask


def normal_mode(out: Path) -> int:
    """The permission bits ``open(out, "w")`` would leave: an existing regular file keeps its
    own, a new file gets 0666 less the umask."""
    with contextlib.suppress(OSError):
        st = out.stat()
        if stat.S_ISREG(st.st_mode):
            return stat.S_IMODE(st.st_mode)
    return 0o666 & ~current_umask()


def _link_target(out: Path) -> Path:
    """An output named by a symbolic link is written where the link points (the link stays);
    a link to nothing is refused rather than replaced."""
    if not out.is_symlink():
        return out
    try:
        return out.resolve(strict=True)
    except (OSError, RuntimeError):
        raise InputError(f"output {out}: is a symbolic link to nothing (dangling, or a loop); "
                         "refusing to replace the link, give the path to write") from None


@contextlib.contextmanager
def atomic_path(out: PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``out``; on success give it a normal write's mode
    (:func:`normal_mode`) and rename it to ``out``,
    else delete it. The temporary name keeps ``out``'s suffix (some writers pick the format by
    extension). Stale temporaries of ``out`` from killed runs are removed first."""
    out = _link_target(Path(out))
    _check_chars("output", out)
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(out)
    tmp_path: Path | None = None
    try:
        # Ctrl-C / SIGTERM between creating the temporary file and knowing its name would leave
        # it behind: held for those few lines, delivered inside the try (which removes it)
        with deferred_signals():
            fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.stem}.{os.getpid()}-",
                                       suffix=f".tmp{out.suffix}")
            os.close(fd)
            tmp_path = Path(tmp)
        yield tmp_path
        os.chmod(tmp_path, normal_mode(out))
        os.replace(tmp_path, out)
    except OSError as exc:  # name the output, not the temporary file that is gone now
        if tmp_path is None:
            raise
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        if exc.filename not in (str(tmp_path), tmp_path) and exc.filename is not None:
            raise
        raise OSError(exc.errno, exc.strerror or str(exc), str(out)) from exc
    except BaseException:
        if tmp_path is not None:
            with contextlib.suppress(OSError):
                tmp_path.unlink()
        raise


@contextlib.contextmanager
def atomic_write(out: PathLike) -> Iterator:
    """Open a binary stream whose contents replace ``out`` atomically when the block succeeds."""
    with atomic_path(out) as tmp, open(tmp, "wb") as stream:
        yield stream
        stream.flush()
        os.fsync(stream.fileno())
