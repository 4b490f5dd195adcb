"""Exception hierarchy.

The CLI maps :class:`InputError` (bad input, usage or config; exit code 2) and
:class:`ProcessingError` (a valid request that failed while running; exit code 1) to one line on
stderr. Messages name the file or config key and say what was expected.
"""

from __future__ import annotations


class SplatdeformError(Exception):
    """Base class of every error the package raises on purpose."""

    exit_code = 1


class InputError(SplatdeformError):
    """Bad input: missing/unreadable/malformed file, bad config key or value, bad argument."""

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
