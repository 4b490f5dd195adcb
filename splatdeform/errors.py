"""Exception hierarchy.

The CLI maps :class:`InputError` (bad input, usage or config; exit code 2) and
:class:`ProcessingError` (a valid request that failed while running; exit code 1) to one line on
stderr. Messages name the file or config key and say what was expected.
"""

from __future__ import annotations


class SplatdeformError(Exception):
    """Base class of every error the package raises on purpose.

    The parts of the one line the CLI prints are fields, not text to parse: ``file`` (the
    file it is about, e.g. the edit config), ``key`` (the config key path, e.g.
    ``handles[1].region``) and ``message`` (what was wrong and what was expected). str() is
    ``file: key: message`` with the missing parts left out.
    """

    exit_code = 1

    def __init__(self, message: str = "", *, key: str | None = None,
                 file: str | None = None) -> None:
        self.message = message
        self.key = key
        self.file = None if file is None else str(file)
        super().__init__(message)

    @classmethod
    def at(cls, key: str, message: str, *, file: str | None = None) -> SplatdeformError:
        """The error for config key ``key``."""
        return cls(message, key=key, file=file)

    def in_file(self, file: str) -> SplatdeformError:
        """This error, said of ``file`` (kept when it already names one)."""
        if self.file is None:
            self.file = str(file)
        return self

    def __str__(self) -> str:
        return ": ".join(p for p in (self.file, self.key, self.message) if p)

    def __reduce__(self):  # picklable with its fields (batch workers, Dask)
        return (_rebuild, (type(self), self.message, self.key, self.file))


def _rebuild(cls: type, message: str, key: str | None, file: str | None) -> SplatdeformError:
    return cls(message, key=key, file=file)


class InputError(SplatdeformError, ValueError):
    """Bad input: missing/unreadable/malformed file, bad config key or value, bad argument.

    Also a ValueError, so callers of the numeric functions that catch ValueError keep working.
    """

    exit_code = 2


class ConfigError(InputError):
    """A config file or config value is wrong; the message names the key path."""


class FormatError(InputError):
    """A model file cannot be read (malformed header, truncated body, missing properties)."""


class RegionError(InputError):
    """The selected regions cannot define an edit (empty, overlapping, degenerate handle)."""


class DeviceError(InputError):
    """A requested compute or render device does not exist on this machine."""


class ProcessingError(SplatdeformError):
    """A valid request failed while running (numerical failure, out of memory, ...)."""

    exit_code = 1


def error_line(exc: BaseException, *, limit: int | None = None, mark: str = "...") -> str:
    """The one line an error is said in (the CLI, batch rows, archive problems, the editor).

    ``str(exc)`` with every run of whitespace (line breaks included) made one space, or the
    exception's type name when that is empty. With ``limit``, a line of ``limit`` characters or
    more is cut to ``limit`` characters ending in ``mark``. A terminal still needs
    :func:`one_line` for the control characters whitespace does not cover."""
    line = " ".join(str(exc).split()) or type(exc).__name__
    if limit is None or len(line) < limit:
        return line
    return line[:limit - len(mark)] + mark


def one_line(text: str) -> str:
    """``text`` with line breaks and other control characters escaped (``\\n``, ``\\x1b``): a
    path may hold a newline, and an error printed on a terminal must stay one line."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class NoDeviceWarning(RuntimeWarning):
    """``backend: auto`` found no OpenCL device and runs the (slow) numpy reference. A
    RuntimeWarning for callers that filter those, but the CLI shows it (one line), while it
    hides numpy's own RuntimeWarnings."""

