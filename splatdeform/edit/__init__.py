"""The config layer: the only package that knows the edit config.

    YAML --config--> EditConfig --plain (selectors, units, metaphors)--> masks, metaphors,
    transforms, delta_c --> splatdeform.deform --> run (save) / images / cache / stream

- :mod:`.config` / :mod:`.schema`: the pydantic models, YAML reading, key-path errors.
- :mod:`.selectors`: the selector registry (config entry -> model-unit selector -> mask).
- :mod:`.units`: relative units -> model units, in one place.
- :mod:`.metaphors`: the metaphor registry (handle, curve): config -> Metaphor, pose -> delta_c.
- :mod:`.plain`: the one conversion the rest calls. :mod:`.run`: ``run_edit`` (in memory, or
  :mod:`.stream` when the scan exceeds the budget); :mod:`.result`: ``EditResult``, its figures
  (the one stats builder) and the report.
- :mod:`.cache` (``--reuse``), :mod:`.selection` (``select``), :mod:`.images` (``--render``),
  :mod:`.stream` (out-of-core and Dask single-scan deform: labels and orchestration).

Public names are loaded on first use (the CLI parser imports no scipy).
"""

from __future__ import annotations

from splatdeform.lazy import lazy_exports

_LAZY = {
    "run_edit": "run", "EditResult": "result", "format_report": "result", "precompute": "run",
    "EditConfig": "config", "load_edit": "config", "parse_edit": "config",
}


__getattr__ = lazy_exports(__name__, _LAZY)


__all__ = sorted(_LAZY)
