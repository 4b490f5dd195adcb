"""What a scan will cost, judged before it is loaded (or extracted from an archive).

The PLY header is parsed by the PLY module's own header parser (never re-parsed here), and the
file's real size is weighed against it: a header declaring ten vertices followed by 2 GiB of zeros
is refused up front instead of being read into memory. The memory estimate takes the larger of the
header's point count and the file's size, so a lying header cannot slip under the budget.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io import LAS_EXTENSIONS, PLY_EXTENSIONS, extension_of
from ..io.ply_format import MAX_HEADER_BYTES, parse_header

HEAD_BYTES = MAX_HEADER_BYTES + 4096   # enough to hold any header the PLY reader accepts
BYTES_PER_POINT = 2048          # model copies, kNN graph, basis rows, render buffers
BASE_BYTES = 150 * 2**20        # interpreter + numpy + fitting matrices
BYTES_PER_FILE_BYTE = {False: 4, True: 12}   # binary / text: raw bytes, parsed copies, tokens
SLACK_BYTES = 1 << 20           # trailing whitespace the reader tolerates after a binary body


@dataclass(frozen=True)
class Probe:
    """A scan's declared and real size."""

    points: int              # points the header declares (PLY, LAS/LAZ); else a bound from the size
    size: int                # bytes
    text: bool               # ascii PLY or a text format
    max_size: int | None     # largest size the header allows (binary PLY); None: no bound


def _max_count(len_dtype: str) -> int:
    info = np.iinfo(np.dtype(len_dtype))
    return int(info.max)


def probe(name: str, head: bytes, size: int, *, suffix: str | None = None) -> Probe:
    """Judge a scan from its first bytes ``head`` (up to :data:`HEAD_BYTES`) and its ``size``.

    ``name`` names the scan in errors; ``suffix`` (default: the name's) picks the format.
    Raises FormatError (from the PLY header parser) for a malformed PLY header."""
    suffix = (suffix or extension_of(name)).lower()
    if suffix in LAS_EXTENSIONS:
        return Probe(_las_points(head), size, False, None)
    if suffix not in PLY_EXTENSIONS:
        return Probe(size // 12, size, True, None)
    header = parse_header(Path(name), head)
    points = sum(count for el, count, _ in header.elements if el == "vertex")
    if header.text:
        return Probe(points, size, True, None)
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
    return Probe(points, size, False, header.size + body + SLACK_BYTES)


def _las_points(head: bytes) -> int:
    """Point count from a LAS/LAZ header, read by laspy's header parser (a compressed LAZ holds
    3-10x more points than its size suggests); 0 when it cannot be read (the loader will say
    why)."""
    try:
        import laspy

        return int(laspy.LasHeader.read_from(io.BytesIO(head)).point_count)
    except Exception:  # laspy raises its own and struct errors; the loader reports them
        return 0


def estimate_memory(p: Probe) -> int:
    """Peak bytes to deform the scan: the larger of the per-point and the per-file-byte cost."""
    return BASE_BYTES + max(BYTES_PER_POINT * p.points, BYTES_PER_FILE_BYTE[p.text] * p.size)


def check(name: str, p: Probe, budget: float | None, available: float | None = None) -> None:
    """Refuse a scan larger than its header allows, or one that does not fit the memory budget.

    ``budget``: bytes per worker (None: no budget set; then only the file itself must fit in
    ``available`` bytes). Raises InputError with one line naming the scan."""
    mib = 2**20
    if p.max_size is not None and p.size > p.max_size:
        raise InputError(f"{name}: the file is {p.size:,} bytes but its PLY header declares at "
                         f"most {p.max_size:,} (header, element counts and 1 MiB of slack); "
                         "refusing to read it")
    if budget is not None:
        need = estimate_memory(p)
        if need > budget:
            raise InputError(f"{name}: needs about {need / mib:.0f} MiB for {p.points:,} points "
                             f"in {p.size / mib:.0f} MiB, more than the {budget / mib:.0f} MiB "
                             "per worker; use fewer workers or set memory_per_worker_mb")
    elif available is not None:
        need = BASE_BYTES + BYTES_PER_FILE_BYTE[p.text] * p.size
        if need > available:
            raise InputError(f"{name}: a {p.size / mib:.0f} MiB file needs about "
                             f"{need / mib:.0f} MiB, more than the {available / mib:.0f} MiB "
                             "available on this worker")
