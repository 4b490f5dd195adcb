"""Locate the run-time source folders ``kernels/`` and ``shaders/``.

From a checkout (or an editable install) they are the top-level folders of the repository; an
installed wheel carries them inside the package as ``splatdeform/_data/<name>``.
"""

from __future__ import annotations

from pathlib import Path

from .errors import InputError

_PACKAGE_DIR = Path(__file__).resolve().parent


def resource_dir(name: str) -> Path:
    """Return the folder holding the run-time sources ``name`` ("kernels" or "shaders")."""
    if name not in ("kernels", "shaders"):
        raise InputError(f"resource name: expected 'kernels' or 'shaders', got {name!r}")
    for candidate in (_PACKAGE_DIR / "_data" / name, _PACKAGE_DIR.parent / name):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(
        f"{name}/ not found next to the splatdeform package ({_PACKAGE_DIR}); reinstall it"
    )


def resource_path(name: str, filename: str) -> Path:
    """Path of one run-time source file, e.g. ``resource_path("kernels", "basis.cl")``."""
    path = resource_dir(name) / filename
    if not path.is_file():
        raise FileNotFoundError(f"{path}: run-time source file missing; reinstall splatdeform")
    return path
