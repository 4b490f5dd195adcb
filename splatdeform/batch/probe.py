"""What a scan will cost, judged before it is loaded (or extracted from an archive).

The PLY header is parsed by the PLY module's own header parser (never re-parsed here), and the
file's real size is weighed against it: a header declaring ten vertices followed by 2 GiB of zeros
is refused up front instead of being read into memory. The memory figure is the one estimator's
(:mod:`splatdeform.memory`), which counts ASCII and list amplification and takes the larger of
the header's counts and what the size can hold, so a lying header cannot slip under the budget.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io import LAS_EXTENSIONS, PLY_EXTENSIONS, extension_of
from ..io.ply_format import parse_header
from ..memory import HEAD_BYTES, FileCost, deform_peak, head_cost
from ..rbf.defaults import DEFAULT_MAX_CENTERS

__all__ = ["HEAD_BYTES", "Probe", "check", "estimate_memory", "probe"]
SLACK_BYTES = 1 << 20           # trailing whitespace the reader tolerates after a binary body


@dataclass(frozen=True)
class Probe:
    """A scan's declared and real size, and its cost."""

    cost: FileCost
    text: bool               # ascii PLY or a text format
    max_size: int | None     # largest size the header allows (binary PLY); None: no bound

    @property
    def points(self) -> int:
        return self.cost.points

    @property
    def size(self) -> int:
        return self.cost.size


def _max_count(len_dtype: str) -> int:
    return int(np.iinfo(np.dtype(len_dtype)).max)


def probe(name: str, head: bytes, size: int, *, suffix: str | None = None) -> Probe:
    """Judge a scan from its first bytes ``head`` (up to :data:`HEAD_BYTES`) and its ``size``.

    ``name`` names the scan in errors; ``suffix`` (the format's extension, by
    :func:`splatdeform.io.extension_of`; default: the name's) picks the format.
    Raises FormatError (from the PLY header parser) for a malformed PLY header."""
    ext = (suffix or extension_of(name)).lower()
    cost = head_cost(name, head, size, ext)
    if ext in LAS_EXTENSIONS:
        return Probe(cost, False, None)
    if ext not in PLY_EXTENSIONS:
        return Probe(cost, True, None)
    header = parse_header(Path(name), head)   # head_cost refused a header declaring more
    if header.text:                           # than the file holds (the PLY probe's check)
        return Probe(cost, True, None)
    body = 0
    for _, count, props in header.elements:
        row = 0
        for p in props:
            if p.is_list:
                row += np.dtype(p.len_dtype).itemsize + \
                    _max_count(p.len_dtype) * np.dtype(p.dtype).itemsize
            else:
                row += np.dtype(p.dtype).itemsize
        body += count * row
    return Probe(cost, False, header.size + body + SLACK_BYTES)


def estimate_memory(p: Probe, max_centers: int = DEFAULT_MAX_CENTERS) -> int:
    """Peak bytes to deform the scan, the interpreter included (``max_centers``: the edit's
    ``fit.max_centers``)."""
    return deform_peak(p.cost, max_centers=max_centers)


def check(name: str, p: Probe) -> None:
    """Refuse a scan larger than its header allows (one InputError line naming it). Whether it
    fits the memory budget is the one budget rule's (:func:`splatdeform.memory.choose`, asked by
    the runner and the worker)."""
    if p.max_size is not None and p.size > p.max_size:
        raise InputError(f"{name}: the file is {p.size:,} bytes but its PLY header declares at "
                         f"most {p.max_size:,} (header, element counts and 1 MiB of slack); "
                         "refusing to read it")
