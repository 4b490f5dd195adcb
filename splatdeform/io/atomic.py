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
- The temporary file is created exclusively (``O_EXCL | O_NOFOLLOW``) in the opened output
  folder and renamed by that folder's descriptor: a symbolic link that appears at an output's
  name after the checks (planted by someone else) is replaced by the rename, never written
  through. Stream writers (:func:`atomic_write`) write through the temporary file's descriptor;
  writers given a path (:func:`atomic_path`) that find a link there are refused before the
  rename. A folder made for an output is removed again when the write fails.
- An output the user *named* as a symbolic link is written where it pointed when
  :func:`check_io_paths` ran (the link stays); a dangling link is refused, never replaced.
  Inside :func:`pinned_outputs` (the editor's Save) a link is never followed: an output that
  is a link is refused, and each output folder is opened at check time and written through
  that descriptor, so a folder swapped for a link afterwards is not followed either.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import stat
import threading
from collections.abc import Callable, Iterable, Iterator
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
        _plan_output(what, out)
        for in_what, inp in ins:
            if _same(out, inp):
                raise InputError(f"{what} {out}: is the {in_what} ({inp}); refusing to overwrite "
                                 "an input, choose another output path")
        for other_what, other in outs[:i]:
            if _same(out, other):
                raise InputError(f"{what} {out}: is also the {other_what} output; choose "
                                 "different output paths")
    if after_checks_hook is not None:
        after_checks_hook([out for _, out in outs])


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


def _remove_dead(folder: Path, names: Iterable[str], out: Path | None,
                 dir_fd: int | None = None) -> list[Path]:
    removed = []
    for name in names:
        pid = temp_owner(name, out)
        if pid is None or pid_alive(pid):
            continue
        p = folder / name
        with contextlib.suppress(OSError):
            if stat.S_ISREG(os.stat(name if dir_fd is not None else p, dir_fd=dir_fd,
                                    follow_symlinks=False).st_mode):
                os.unlink(name if dir_fd is not None else p, dir_fd=dir_fd)
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
    # cheap filter first: output folders of a batch hold many files
    return _remove_dead(folder, _candidates(names, out), out)


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


# ------------------------------------------------------------------------ links and folders

_NAMED_LINKS: dict[str, Path] = {}   # abspath of an output named as a link -> its target then
_NAMED_LOCK = threading.Lock()
_local = threading.local()            # .pinned: the _Pinned scope of this thread, if any

#: Test seams (None in normal runs): called with the checked outputs when
#: :func:`check_io_paths` has passed, and with the output right before :func:`atomic_path`'s
#: rename, so a test can plant a link exactly there.
after_checks_hook: Callable[[list[Path]], None] | None = None
before_rename_hook: Callable[[Path], None] | None = None


class _Pinned:
    """Opened folders of one :func:`pinned_outputs` block (abspath -> O_DIRECTORY fd)."""

    def __init__(self) -> None:
        self.fds: dict[str, int] = {}


@contextlib.contextmanager
def pinned_outputs() -> Iterator[None]:
    """Within the block, on this thread: no output is ever reached through a symbolic link.
    :func:`check_io_paths` refuses an output that is a link, and opens each output's folder
    (refused when that folder is itself a link) and keeps it open; :func:`atomic_path` writes
    relative to that opened folder, so a folder swapped for a link afterwards is not followed,
    and a link that appears at an output's name is replaced by the rename, never followed.
    The editor's Save runs in one."""
    prev = getattr(_local, "pinned", None)
    scope = _Pinned()
    _local.pinned = scope
    try:
        yield
    finally:
        _local.pinned = prev
        for fd in scope.fds.values():
            with contextlib.suppress(OSError):
                os.close(fd)


def _flags(*names: str) -> int:
    return sum(getattr(os, n, 0) for n in names)


_DIR_FLAGS = _flags("O_RDONLY", "O_DIRECTORY", "O_CLOEXEC")


def _plan_output(what: str, out: Path) -> None:
    """Check time: a link named as an output is resolved now (written where it points now,
    whatever it points to later); inside :func:`pinned_outputs` it is refused instead, and the
    output's folder is opened and kept."""
    scope = getattr(_local, "pinned", None)
    if scope is None:
        if out.is_symlink():
            with _NAMED_LOCK:
                _NAMED_LINKS[os.path.abspath(out)] = out.resolve(strict=True)
        return
    if out.is_symlink():
        raise InputError(f"{what} {out}: is a symbolic link; refusing to write through a "
                         "link, choose another name")
    key = os.path.abspath(out.parent)
    if key in scope.fds or _stat(out.parent) is None:
        return   # already open, or made by the writer
    try:
        scope.fds[key] = os.open(key, _DIR_FLAGS | _flags("O_NOFOLLOW"))
    except OSError as exc:
        raise InputError(f"{what} {out}: its folder {out.parent} could not be opened "
                         f"({exc.strerror or exc}; a symbolic link is not followed)") from None


def _named_target(out: Path) -> Path:
    """Write time: where ``out`` is written. A link named as the output at check time goes to
    the file it pointed to then; any other link (one planted after the checks) is never
    followed: the rename replaces it."""
    if getattr(_local, "pinned", None) is not None or not out.is_symlink():
        return out
    with _NAMED_LOCK:
        return _NAMED_LINKS.get(os.path.abspath(out), out)


def _make_folders(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; the ones made, outermost first."""
    missing = []
    while _stat(folder) is None and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    made = []
    for f in reversed(missing):
        try:
            f.mkdir()
        except FileExistsError:
            continue
        made.append(f)
    return made


def _remove_folders(made: list[Path]) -> None:
    for f in reversed(made):   # innermost first; only while empty
        with contextlib.suppress(OSError):
            f.rmdir()


def _open_folder(folder: Path) -> int:
    scope = getattr(_local, "pinned", None)
    if scope is not None:
        fd = scope.fds.get(os.path.abspath(folder))
        if fd is not None:
            return os.dup(fd)
        return os.open(folder, _DIR_FLAGS | _flags("O_NOFOLLOW"))
    return os.open(folder, _DIR_FLAGS)


_ALPHABET = "abcdefghijklmnopqrstuvwxyz0123456789_"   # tempfile's (RANDOM_CHARS)


def _random_name(n: int) -> str:
    """``n`` characters of :data:`_ALPHABET`, uniform, from the OS's random bytes (what
    ``secrets.choice`` draws from, without importing secrets' hashlib and hmac: ~5 ms of every
    write's start-up)."""
    top = 256 - 256 % len(_ALPHABET)   # bytes at or above are dropped: no bias
    chars: list[str] = []
    while len(chars) < n:
        chars += [_ALPHABET[b % len(_ALPHABET)] for b in os.urandom(2 * n) if b < top]
    return "".join(chars[:n])


def _create_temp(dfd: int, out: Path) -> tuple[int, str]:
    """A new temporary file in the opened folder, created exclusively (never a link, never an
    existing file): (its fd, its name)."""
    prefix, suffix = f".{out.stem}.{os.getpid()}-", f".tmp{out.suffix}"
    flags = _flags("O_RDWR", "O_CREAT", "O_EXCL", "O_NOFOLLOW", "O_CLOEXEC")
    for _ in range(100):
        name = prefix + _random_name(RANDOM_LEN) + suffix
        try:
            return os.open(name, flags, 0o600, dir_fd=dfd), name
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary file name", str(out))


def _mode_in(dfd: int, name: str) -> int:
    """:func:`normal_mode` of the entry ``name`` of the opened folder (never through a link)."""
    with contextlib.suppress(OSError):
        st = os.stat(name, dir_fd=dfd, follow_symlinks=False)
        if stat.S_ISREG(st.st_mode):
            return stat.S_IMODE(st.st_mode)
    return 0o666 & ~current_umask()


def _temp_path(out: Path, dfd: int, name: str) -> Path:
    """The temporary file's path for writers that open it by name: through the opened folder
    (``/proc/self/fd``) inside :func:`pinned_outputs` where Linux offers it, else beside
    ``out``."""
    if getattr(_local, "pinned", None) is not None and os.path.isdir(f"/proc/self/fd/{dfd}"):
        return Path(f"/proc/self/fd/{dfd}") / name
    return out.parent / name


@contextlib.contextmanager
def _atomic(out: PathLike) -> Iterator[tuple[Path, int]]:
    """(temporary path, its open fd); see :func:`atomic_path`."""
    out = Path(out)
    _check_chars("output", out)
    out = _named_target(out)
    own = True   # an OSError of our own steps names the output
    made: list[Path] = []
    dfd = fd = -1
    name: str | None = None
    tmp_path: Path | None = None
    done = False
    try:
        made = _make_folders(out.parent)
        dfd = _open_folder(out.parent)
        _remove_dead(out.parent, _candidates(os.listdir(dfd), out), out, dfd)
        # Ctrl-C / SIGTERM between creating the temporary file and knowing its name would leave
        # it behind: held for those few lines, delivered inside the try (which removes it)
        with deferred_signals():
            fd, name = _create_temp(dfd, out)
        tmp_path = _temp_path(out, dfd, name)
        own = False
        yield tmp_path, fd
        own = True
        st = os.stat(name, dir_fd=dfd, follow_symlinks=False)
        if not stat.S_ISREG(st.st_mode):
            raise InputError(f"output {out}: its temporary file was replaced by something "
                             "else than a file while it was written; nothing was written")
        os.fchmod(fd, _mode_in(dfd, out.name))
        if before_rename_hook is not None:
            before_rename_hook(out)
        # by the opened folder: replaces whatever entry ``out`` is now (a link planted since
        # the checks included), never writes through it
        os.replace(name, out.name, src_dir_fd=dfd, dst_dir_fd=dfd)
        done = True
    except OSError as exc:  # name the output, not the temporary file
        if not own and exc.filename not in (str(tmp_path), name) and exc.filename is not None:
            raise
        raise OSError(exc.errno, exc.strerror or str(exc), str(out)) from exc
    finally:
        if not done and name is not None:
            with contextlib.suppress(OSError):
                os.unlink(name, dir_fd=dfd)
        for f in (fd, dfd):
            if f >= 0:
                with contextlib.suppress(OSError):
                    os.close(f)
        if not done:
            _remove_folders(made)


def _candidates(names: Iterable[str], out: Path) -> list[str]:
    prefix, suffix = f".{out.stem}.", f".tmp{out.suffix}"
    return [n for n in names if n.startswith(prefix) and n.endswith(suffix)]


@contextlib.contextmanager
def atomic_path(out: PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``out``; on success give it a normal write's mode
    (:func:`normal_mode`) and rename it to ``out``, else delete it (and the folders made for
    it). The temporary name keeps ``out``'s suffix (some writers pick the format by
    extension). Stale temporaries of ``out`` from killed runs are removed first.

    The temporary file is created exclusively in the opened folder (never a link), and the
    rename is made relative to that folder: a link that appears at ``out`` after the checks is
    replaced, never written through. A link that :func:`check_io_paths` saw named as the output
    is written where it pointed then. Writers given the path open the temporary file by name;
    one replaced by a link meanwhile is refused before the rename (:func:`atomic_write`'s stream
    never opens it by name)."""
    with _atomic(out) as (tmp, _):
        yield tmp


@contextlib.contextmanager
def atomic_write(out: PathLike) -> Iterator:
    """Open a binary stream whose contents replace ``out`` atomically when the block succeeds
    (the exclusive temporary file of :func:`atomic_path`, written through its descriptor)."""
    with _atomic(out) as (_, fd), os.fdopen(os.dup(fd), "wb") as stream:
        yield stream
        stream.flush()
        os.fsync(stream.fileno())
