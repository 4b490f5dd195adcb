"""Packages export their public names lazily (imported on first use), so that importing one
submodule, or running ``splatdeform info``, does not load scipy, the fitter or the renderer."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def lazy_exports(package: str, names: dict[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` for ``package`` that imports ``names[name]`` (a submodule,
    relative to the package, or an absolute ``splatdeform.…`` name) on first access and caches
    the value in the package. A name not in ``names`` raises AttributeError, so ``from package
    import submodule`` still finds a submodule."""
    top = package.partition(".")[0] + "."

    def __getattr__(name: str) -> Any:
        module = names.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        where = module if module.startswith(top) else f".{module}"
        value = getattr(importlib.import_module(where, package), name)
        setattr(importlib.import_module(package), name, value)
        return value

    return __getattr__
