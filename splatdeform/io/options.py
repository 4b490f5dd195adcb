"""Write options of the quantising and PCD writers, for one block of saves.

``save:`` in an edit config (and ``deform --spz-version``) chooses, per run, the SPZ version
(3 for older readers, 4 by default), the SOG SH encoder (``reference`` by default, ``fast``),
the SOG splat order (``morton`` by default, ``keep``) and the PCD DATA encoding (the input's
own by default). Each writer keeps its choice in a context variable; :func:`writing` sets
those that are given, importing a format's module only when its option is set (a verb still
imports only the formats it opens).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator


@contextlib.contextmanager
def writing(*, spz_version: int | None = None, sog_quality: str | None = None,
            sog_order: str | None = None, pcd_data: str | None = None) -> Iterator[None]:
    """Saves inside the block use these options (None: the writer's default)."""
    with contextlib.ExitStack() as stack:
        if spz_version is not None:
            from .spz import writing_version

            stack.enter_context(writing_version(spz_version))
        if sog_quality is not None:
            from .sog import quality

            stack.enter_context(quality(sog_quality))
        if sog_order is not None:
            from .sog_order import order

            stack.enter_context(order(sog_order))
        if pcd_data is not None:
            from .pcd import data_encoding

            stack.enter_context(data_encoding(pcd_data))
        yield
