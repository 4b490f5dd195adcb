"""Shared test fixtures.

Real scans live in ``../shared/data`` beside the checkout; tests that need them skip with a clear
reason only when that folder is absent (a user's fresh clone). Generated fixtures come from
``data_tools/`` and are written to pytest's tmp folders, never into the repository.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"

if str(ROOT) not in sys.path:  # data_tools/ is a top-level folder, not part of the package
    sys.path.insert(0, str(ROOT))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ../shared/data; skips the test when the folder is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (fresh clone without ../shared)")
    return SHARED_DATA


def bar_edit(transform: dict | None = None, *, fit: dict | None = None,
             backend: str | None = "numpy", **keys) -> dict:
    """The edit most tests run on a bar along x (a fresh dict to change or dump as YAML): the
    quarter at x <= 0.25 fixed, the quarter at x >= 0.75 the handle (relative units),
    ``transform`` the handle's (default: a small translation), ``fit`` the fit settings
    (default: tolerance 1e-3), ``backend`` (None: left out); ``keys``: other top-level keys
    (input, output, ...)."""
    import copy

    edit = {"regions": {"units": "relative",
                        "fixed": [{"box": {"min": [0, 0, 0], "max": [0.25, 1, 1]}}],
                        "handle": [{"box": {"min": [0.75, 0, 0], "max": [1, 1, 1]}}]},
            "handle": {"transform": copy.deepcopy(transform or {"translate": [0, 0.1, 0]})},
            "fit": copy.deepcopy({"tolerance": 1e-3} if fit is None else fit)}
    if backend is not None:
        edit["backend"] = backend
    return {**keys, **edit}


def shared_file(relative: str) -> Path:
    """A file under ../shared/data: skips when the whole folder is absent (a fresh clone), fails
    when the folder is there but the file is not (a renamed or lost file must not pass as a
    skip)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (fresh clone without ../shared)")
    path = SHARED_DATA / relative
    if not path.is_file():
        pytest.fail(f"real data file {path} is missing from {SHARED_DATA}")
    return path


def egl_renderer(size: tuple[int, int]):
    """A real Renderer on the EGL context; a missing EGL device fails the test loudly."""
    from splatdeform.errors import DeviceError
    from splatdeform.render.context import get_context
    from splatdeform.render.renderer import Renderer

    try:
        get_context()
    except DeviceError as exc:
        pytest.fail(f"OpenGL via EGL is required for rendering tests: {exc}")
    return Renderer(size)


@pytest.fixture(scope="session")
def oracle() -> list[str]:
    """The splat-transform argv prefix (the splat formats' independent oracle, pinned, installed
    by ``make oracle``); fails (never skips) when it is not installed."""
    from data_tools import splat_transform

    try:
        splat_transform.install()
        return splat_transform.command()
    except splat_transform.OracleMissing as exc:
        pytest.fail(f"the splat-transform oracle is required: {exc}")
