"""The one memory estimator: what loading, deforming or rendering a file will cost, judged from
its header and size before anything is read.

Every budget decision goes through here: ``deform``'s stream-or-not choice, the batch per-worker
guard, and the render budget (sample or not). The figures are peaks in bytes of resident memory
above the interpreter's own (see :data:`BASE_BYTES`), so a caller compares
``BASE_BYTES + estimate`` with its budget.

A header can lie and a body can amplify: ASCII values and PLY list rows cost several times
their bytes once parsed, so the load estimate takes the larger of what the header's counts
imply and what the file's size can hold.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from .rbf.defaults import DEFAULT_MAX_CENTERS

BASE_BYTES = 150 * 2**20   # interpreter + numpy + scipy + pyopencl resident (measured)

# Per point of the in-memory deform beyond the loaded model: float64 geometry and its deformed
# copy, the kNN graph (~(k+1)*16*3 bytes), basis values and Jacobians of the free points.
DEFORM_BYTES_PER_POINT = 300
KNN_BYTES_PER_NEIGHBOR = 16
FIT_BYTES_PER_CENTER = 128 * 2**10   # the fit's working set per allowed center (fit.max_centers)

# Streaming (deform's out-of-core path): per point of a chunk beyond ~4 copies of its record
# (float64 geometry, basis values and Jacobians); per border point (positions, kNN, labels); per
# handle point kept whole for the frame (24 bytes, ~4 copies in the frame's SVD).
STREAM_BYTES_PER_POINT = 900
BORDER_BYTES_PER_POINT = 500
HANDLE_BYTES_PER_POINT = 100

# Per point of an in-memory render beyond its decoded record: float64 positions and their
# float32 copy, normals, splat axes, colours, the kNN spacing query (k + 1 distances and
# indices) and the GL buffers' client copies. Measured (tests/test_render_budget.py checks
# it stays an upper bound): 530-880 bytes a point all in (load included; malloc arenas vary
# with load) for a 300k LAS cloud needing PCA normals, ~220 beyond LARGE_CLOUD points (flat
# discs, no per-point kNN), above a ~255 MB interpreter + EGL base.
RENDER_BYTES_PER_POINT = 768


@dataclass(frozen=True)
class FileCost:
    """What a file holds and what reading it costs.

    points: points the header declares (else a bound from the size); size: file bytes;
    record_bytes: bytes per point once decoded (the model's per-point arrays);
    load_bytes: peak bytes to read the whole file into a PointModel."""

    points: int
    size: int
    record_bytes: int
    load_bytes: int


HEAD_BYTES = 2**20 + 4096   # enough to hold any header the readers accept (PLY: 1 MiB)

# Measured parse costs of the PLY reader (tests/test_memory.py checks them as upper bounds):
ASCII_BYTES_PER_TOKEN = 64    # a bytes object and its list slot from split(), the float64 value
ASCII_BYTES_PER_LINE = 64     # a bytes object per body line and its slot in two lists
LIST_BYTES_PER_ROW = 400     # one numpy array object per non-empty list row (np.split views,
                              # the object column), row offsets and lengths (measured ~350)
LIST_BYTES_PER_VALUE = 8      # a gather index (int64) per list value
LIST_BYTES_PER_ITEM_BYTE = 10  # per byte of a list value: its byte indices (int64) and copies
COPIES_OF_FILE = 3            # binary: the raw bytes, a copied body, the decoded columns
ASCII_COPIES_OF_FILE = 5      # ascii: raw bytes, split lines, joined rows, tokens, values


def file_cost(path: str | Path) -> FileCost:
    """Judge ``path`` from its header and size (no body is read).

    Raises InputError/FormatError (one line naming the file) for an unreadable header."""
    path = Path(path)
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        head = fh.read(HEAD_BYTES)
    return head_cost(path, head, size)


def head_cost(name: str | Path, head: bytes, size: int, suffix: str | None = None) -> FileCost:
    """:func:`file_cost` from the file's first bytes ``head`` (up to :data:`HEAD_BYTES`) and its
    ``size``: what the batch guard uses for an archive member before extracting it.
    ``suffix`` (default: the name's) picks the format."""
    from .io import LAS_EXTENSIONS, PLY_EXTENSIONS, extension_of

    suffix = (suffix or extension_of(name)).lower()
    if suffix in PLY_EXTENSIONS:
        return _ply_cost(Path(name), head, size)
    if suffix in LAS_EXTENSIONS:
        return _las_cost(head, size)
    points = max(size // 12, 1)
    return FileCost(points, size, 24, 4 * size + 48 * points)


def _ply_cost(path: Path, head: bytes, size: int) -> FileCost:
    """The PLY reader's peak from the header's counts and the file's size: binary rows are
    copied once, but every non-empty list row becomes an array object and an ASCII token a
    Python bytes object (tens of bytes for a two-byte token), so a list- or token-dense body
    costs up to ~30x its size. Counts are bounded by what the size can hold, so a lying
    header cannot make the estimate small."""
    import numpy as np

    from .io.ply_format import parse_header

    header = parse_header(path, head)
    body = max(size - header.size, 0)
    points = sum(count for el, count, _ in header.elements if el == "vertex")
    record = 0
    for el, _, props in header.elements:
        if el == "vertex":
            record = sum(np.dtype(p.dtype).itemsize for p in props if not p.is_list)
    record = max(record, 12) + 48   # float64 positions and normals beside the stored columns
    load = (ASCII_COPIES_OF_FILE if header.text else COPIES_OF_FILE) * size
    if header.text:
        tokens = min(body // 2 + 1, sum(count * len(props) for _, count, props in
                                        header.elements
                                        if not any(p.is_list for p in props)))
        if any(p.is_list for _, _, props in header.elements for p in props):
            tokens = body // 2 + 1   # list values: as many tokens as the body can hold
        lines = min(body // 2 + 1, sum(count for _, count, _ in header.elements))
        load += tokens * ASCII_BYTES_PER_TOKEN + lines * ASCII_BYTES_PER_LINE
    else:
        for _, count, props in header.elements:
            lists = [p for p in props if p.is_list]
            if not lists:
                continue
            smallest = min(np.dtype(p.dtype).itemsize for p in lists)
            values = body // smallest
            rows = min(count, body // max(1, sum(np.dtype(p.len_dtype).itemsize
                                                 for p in lists)))
            load += rows * (LIST_BYTES_PER_ROW * len(lists) + 16 * len(props)) + \
                values * (LIST_BYTES_PER_VALUE + LIST_BYTES_PER_ITEM_BYTE * smallest)
    return FileCost(points, size, record, max(load, 2 * size + points * record))


def _las_cost(head: bytes, size: int) -> FileCost:
    """LAS/LAZ from laspy's header parser: the point records (decompressed for LAZ, which holds
    3-10x more points than its size suggests) and their decoded columns."""
    import io

    try:
        import laspy

        header = laspy.LasHeader.read_from(io.BytesIO(head))
        points, record = int(header.point_count), int(header.point_format.size)
    except Exception:  # noqa: BLE001 - the loader reports a bad header with its own message
        points, record = max(size // 20, 1), 20
    record_bytes = record + 24 + 8   # raw record, float64 positions, decoded attributes
    return FileCost(points, size, record_bytes, 3 * points * record + points * 32 + size)


def deform_bytes(cost: FileCost, neighbors: int = 10,
                 max_centers: int = DEFAULT_MAX_CENTERS) -> int:
    """Peak bytes of the in-memory ``deform`` of a file of this cost (above BASE_BYTES): the
    load, the per-point arrays, and the fit's matrices (constraint rows x centers, with the
    modules the run imports on the way; measured up to ~200 MiB at 2000 centers whatever the
    point count, see tests/test_memory.py)."""
    per_point = DEFORM_BYTES_PER_POINT + KNN_BYTES_PER_NEIGHBOR * 3 * (neighbors + 1)
    return cost.load_bytes + cost.points * (per_point + cost.record_bytes) + \
        FIT_BYTES_PER_CENTER * max_centers


def deform_peak(cost: FileCost, neighbors: int = 10,
                max_centers: int = DEFAULT_MAX_CENTERS) -> int:
    """Peak bytes of the whole process for an in-memory ``deform``: :data:`BASE_BYTES` plus
    :func:`deform_bytes` (what the stream-or-not choice and the batch guard compare)."""
    return BASE_BYTES + deform_bytes(cost, neighbors, max_centers)


def stream_chunk(budget: int, record_bytes: int, fixed_bytes: int) -> int:
    """Points per streamed chunk so that a chunk's working set (~4 copies of a record plus
    :data:`STREAM_BYTES_PER_POINT`) takes a quarter of what ``fixed_bytes`` leaves of
    ``budget``; between 5,000 and 4,000,000."""
    left = max(budget - fixed_bytes, budget // 4)
    per_point = 4 * record_bytes + STREAM_BYTES_PER_POINT
    return int(min(max(left // 4 // per_point, 5_000), 4_000_000))


def stream_caps(budget: int, fixed_bytes: int) -> tuple[int, int]:
    """(border points, handle points kept whole) a streamed edit may hold in ``budget`` bytes
    beside ``fixed_bytes``: the border set takes what is left, the whole handle a quarter."""
    left = max(budget - fixed_bytes, budget // 2)
    return int(left // BORDER_BYTES_PER_POINT), int(left // 4 // HANDLE_BYTES_PER_POINT)


def render_bytes(points: int, record_bytes: int = 64) -> int:
    """Peak bytes of rendering ``points`` points in memory (above BASE_BYTES)."""
    return points * (RENDER_BYTES_PER_POINT + record_bytes)


def render_points(budget: int, cost: FileCost, reserve: int = 0) -> int:
    """How many of the file's points a render can hold within ``budget`` bytes (all of them
    when the whole file fits; else a sample size, at least 1). The budget is for the data: the
    interpreter and GL context come on top (a render's peak is about budget + 300 MB).
    ``reserve``: bytes the caller needs besides (e.g. the streamed reader's chunk)."""
    left = budget - reserve
    if left >= cost.load_bytes + render_bytes(cost.points, cost.record_bytes):
        return cost.points
    # a sample is held as raw records (record_bytes) plus the render's own arrays
    return int(max(left, 0) // (render_bytes(1, cost.record_bytes) + cost.record_bytes)) or 1
