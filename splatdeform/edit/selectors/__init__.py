"""Region selectors: a registry of config entries that build model-unit selectors, and their
union as a mask.

``all`` (intersection) and ``not`` (complement) take selectors themselves, nested to any depth;
:func:`leaves` and :func:`map_leaves` walk such a tree (the streaming path swaps its index
leaves for per-chunk masks).

A region is a list of selectors; the config spells each one as a single-key mapping
(``{box: {min, max}}``). Each selector is one module here holding its config entry (pydantic),
its plain selector (a frozen dataclass with ``mask(model, base_dir)``, ``in_units(units,
frame)`` and ``to_config()``) and its ``NAME``; :data:`REGISTRY` lists the modules, and
:data:`SelectorCfg` is the tagged union the edit config validates against. A new selector is
one module plus one line in :data:`REGISTRY`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Union

import numpy as np
from pydantic import Discriminator, Tag

from splatdeform.edit.selectors import all_of, box, indices, not_, plane, prop, sphere
from splatdeform.edit.selectors.all_of import All
from splatdeform.edit.selectors.box import Box
from splatdeform.edit.selectors.indices import Indices
from splatdeform.edit.selectors.not_ import Not
from splatdeform.edit.selectors.plane import Plane
from splatdeform.edit.selectors.prop import Property
from splatdeform.edit.selectors.sphere import Sphere
from splatdeform.model import PointModel

REGISTRY = {m.NAME: m for m in (box, sphere, plane, indices, prop, all_of, not_)}  # one per line

Selector = Box | Sphere | Plane | Indices | Property | All | Not
_TAG = " selector"  # tags are not config keys, so error paths leave them out


def _which(value: Any) -> str | None:
    """The registry name of a ``{name: {...}}`` mapping (None: not exactly one known key)."""
    if isinstance(value, dict):
        known = [k for k in value if k in REGISTRY]  # other keys: unknown keys of that entry
        return known[0] + _TAG if len(known) == 1 else None
    name = getattr(value, "NAME", None) or next(
        (n for n, m in REGISTRY.items() if isinstance(value, m.Entry)), None)
    return None if name is None else name + _TAG


SelectorCfg = Annotated[
    Union[tuple(Annotated[m.Entry, Tag(n + _TAG)] for n, m in REGISTRY.items())],  # noqa: UP007
    Discriminator(_which, custom_error_type="selector",
                  custom_error_message="expected exactly one of " + ", ".join(REGISTRY)),
]
for _m in (all_of, not_):  # the combining selectors hold selectors: resolve the recursion
    _m.Entry.model_rebuild(_types_namespace={"SelectorCfg": SelectorCfg})


def leaves(sel) -> list:
    """The plain (non-combining) selectors of ``sel``, depth first."""
    if isinstance(sel, All):
        return [leaf for part in sel.parts for leaf in leaves(part)]
    if isinstance(sel, Not):
        return leaves(sel.part)
    return [sel]


def map_leaves(sel, fn):
    """``sel`` with every plain selector replaced by ``fn(leaf)`` (the tree kept)."""
    if isinstance(sel, All):
        return All(tuple(map_leaves(p, fn) for p in sel.parts))
    if isinstance(sel, Not):
        return Not(map_leaves(sel.part, fn))
    return fn(sel)


def select(model: PointModel, selectors: list, units: str = "model",
           base_dir: Path | None = None) -> np.ndarray:
    """Union of selectors -> mask (N,) bool.

    ``units="relative"`` is a convenience for API callers: each selector is first put in model
    units (:meth:`in_units`; the config layer converts before calling, with "model").

    Parameters
    ----------
    model : PointModel
        The model whose points are selected.
    selectors : list
        :class:`Box`, :class:`Sphere`, :class:`Plane`, :class:`Indices`, :class:`Property`
        (and their combinations); a point is selected when any of them selects it.
    units : {"model", "relative"}
        The units the selectors are written in ("relative": bounding-box coordinates).
    base_dir : Path, optional
        Where relative file paths in the selectors (an indices file) start.

    Returns
    -------
    ndarray of bool, shape (N,)
        The union of the selectors' masks.

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar
    >>> bar = bumpy_bar(2000)                        # a bumpy cylinder, x in [0, 4]
    >>> ends = sd.select(bar, [sd.Box(min=(-1, -1, -1), max=(0.5, 1, 1)),
    ...                        sd.Sphere(center=(4, 0, 0), radius=0.6)])
    >>> ends.shape, ends.dtype
    ((2000,), dtype('bool'))
    >>> x = bar.positions[ends, 0]
    >>> bool(((x <= 0.5) | (x >= 3.4)).all())
    True
    >>> last = sd.select(bar, [sd.Box(min=(0.75, 0, 0), max=(1, 1, 1))], units="relative")
    >>> bool(bar.positions[last, 0].min() >= 3)
    True
    """
    if units != "model":
        from splatdeform.edit.units import Frame

        frame = Frame.of(model)
        selectors = [s.in_units(units, frame) for s in selectors]
    mask = np.zeros(model.n_points, dtype=bool)
    for sel in selectors:
        mask |= sel.mask(model, base_dir)
    return mask


__all__ = ["REGISTRY", "All", "Box", "Indices", "Not", "Plane", "Property", "Selector",
           "SelectorCfg", "Sphere", "leaves", "map_leaves", "select"]
