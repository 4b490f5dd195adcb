"""The one memory estimator: what loading, deforming or rendering a file will cost, judged from
its header and size before anything is read.

Every budget decision goes through here: ``deform``'s stream-or-not choice, the batch per-worker
guard, and the render budget (sample or not). The figures are peaks in bytes of resident memory
above the interpreter's own (see :data:`BASE_BYTES`), so a caller compares
``BASE_BYTES + estimate`` with its budget.

The budget policy lives here too: sizes (:func:`parse_size`), the machine's memory and the
default budget (:func:`default_budget`, half the RAM), the margin a run may exceed its budget by
(:data:`BUDGET_MARGIN`) and the one rule (:func:`choose`) that decides in memory / stream /
refuse for ``deform``, ``render`` (through :func:`render_points`) and batch.

Every file an estimate reads is opened with :func:`splatdeform.io.regular.open_regular`, and
its header is the reader's own, validated against the file size (LAS/LAZ:
:mod:`splatdeform.io.las_header`, PLY: :func:`splatdeform.io.ply_format.parse_header`, PCD:
:func:`splatdeform.io.pcd.parse_header`): never a second parser that would trust what a header
claims before the checks run.

A header can lie and a body can amplify: ASCII values and PLY list rows cost several times
their bytes once parsed, so the load estimate takes the larger of what the header's counts
imply and what the file's size can hold.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from .errors import ConfigError, FormatError, InputError
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


#: How far above an explicit memory budget a run's peak resident memory may go: the budget is
#: for the data (the model, the fit, a streamed chunk, the border set), and the interpreter with
#: numpy, scipy and the compiled libraries (:data:`BASE_BYTES`, ~150 MB measured) plus the
#: allocator's and the decoders' slack come on top. ``deform --memory-budget B`` (and the
#: config's ``memory_budget``) peaks at most at ``B + BUDGET_MARGIN`` whether it runs in memory
#: (its estimate, interpreter included, is at most B) or streams (chunks and border sized from
#: B); tests/test_hostile_round3_budget.py measures it. A render adds its GL context (see
#: :func:`render_points`).
BUDGET_MARGIN = 256 * 2**20

#: The smallest budget accepted (a smaller one could not hold a streamed chunk).
MIN_BUDGET = 64 * 2**20

_UNITS = {"": 1, "b": 1, "k": 2**10, "kb": 2**10, "kib": 2**10, "m": 2**20, "mb": 2**20,
          "mib": 2**20, "g": 2**30, "gb": 2**30, "gib": 2**30, "t": 2**40, "tb": 2**40,
          "tib": 2**40}


def parse_size(text: str | int | float, what: str = "--memory-budget") -> int:
    """'512MB', '1.5GB', '2g', 1000000 -> bytes (ConfigError naming ``what`` otherwise)."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        value = int(text)
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([a-zA-Z]*)\s*", str(text))
        if not m or m.group(2).lower() not in _UNITS:
            raise ConfigError(f"{what}: expected a size like 512MB or 2GB, got {text!r}")
        value = int(float(m.group(1)) * _UNITS[m.group(2).lower()])
    if value < MIN_BUDGET:
        raise ConfigError(f"{what}: expected at least 64MB, got {text!r}")
    return value


def budget_bytes(flag: int | str | None, config_value: int | str | None = None) -> int | None:
    """The explicit memory budget in bytes: ``--memory-budget`` (``flag``), else the config's
    ``memory_budget``, else None (no explicit budget: the caller's default, half the RAM). A
    malformed value is a ConfigError naming the flag or the key."""
    if flag is not None:
        return parse_size(flag) if isinstance(flag, str) else int(flag)
    return None if config_value is None else parse_size(config_value, "memory_budget")


def machine_memory() -> int:
    """Physical memory in bytes."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8 * 2**30


def default_budget() -> int:
    """Half the machine's RAM: the budget when none is given."""
    return machine_memory() // 2


@dataclass(frozen=True)
class Choice:
    """What :func:`choose` decided: ``mode`` "memory", "stream" or "refuse"; ``need``: the
    in-memory estimate (bytes, interpreter included); ``budget``: the budget it was held to
    (bytes); ``explicit``: given (flag, config key, batch's per-worker figure) rather than the
    default; ``message``: the refusal line (refuse), or the warning (memory over a default
    budget), else ''."""

    mode: str
    need: int
    budget: int
    explicit: bool
    message: str = ""


def _mb(n: float) -> str:
    return f"{n / 2**20:,.0f} MB"


def choose(need: int, budget: int | None, *, streamable: bool, name: str | Path = "input",
           whole: str | None = None, budget_name: str = "--memory-budget",
           why_not: str = "") -> Choice:
    """The one budget rule: in memory, stream, or refuse.

    ``need``: the in-memory estimate (:func:`deform_peak`), ``budget``: the explicit budget in
    bytes (None: the default, half the RAM); ``streamable``: the file's format and the edit
    can stream; ``whole``: the option that needs the whole model in memory (``--reuse``,
    ``--drop-nonfinite``), if any; ``why_not``: why it cannot stream (for the refusal line).

    - the estimate fits: in memory;
    - it does not, and the run can stream (no ``whole``): stream (chunks sized from the budget);
    - an explicit budget is a cap: otherwise refused, one line naming the estimate and the
      budget;
    - the default budget keeps the rule from before the cap: in memory, with a warning when
      ``whole`` is what keeps it there.
    """
    explicit = budget is not None
    limit = int(budget) if explicit else default_budget()
    if need <= limit:
        return Choice("memory", need, limit, explicit)
    if streamable and whole is None:
        return Choice("stream", need, limit, explicit)
    if explicit:
        reason = (f"{whole} needs the whole model in memory" if whole is not None else
                  why_not or "it cannot stream")
        return Choice("refuse", need, limit, explicit,
                      f"{name}: the in-memory estimate is {_mb(need)}, more than the memory "
                      f"budget of {_mb(limit)} ({budget_name}), and {reason}; raise the "
                      "budget or give a smaller scan")
    warning = "" if whole is None else (f"{name}: over the memory budget, but {whole} needs "
                                        "the whole model in memory: running in memory")
    return Choice("memory", need, limit, explicit, warning)


@dataclass(frozen=True)
class FileCost:
    """What a file holds and what reading it costs.

    points: points the header declares (else a bound from the size); size: file bytes;
    record_bytes: bytes per point once decoded (the model's per-point arrays);
    load_bytes: peak bytes to read the whole file into a PointModel;
    reader_bytes: what a streamed reader holds besides the rows it returns (LAZ: one
    compressed chunk, :func:`laz_reader_bytes`)."""

    points: int
    size: int
    record_bytes: int
    load_bytes: int
    reader_bytes: int = 0


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
    """Judge ``path`` from its header and size (no body is read), through the one opener
    (:func:`splatdeform.io.regular.open_regular`: a FIFO or a device is refused, not read).

    Raises InputError/FormatError (one line naming the file) for an unreadable header or one
    that declares more than the file holds."""
    from .io.regular import open_regular

    path = Path(path)
    try:
        with open_regular(path) as fh:
            size = os.fstat(fh.fileno()).st_size
            head = fh.read(HEAD_BYTES)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory; expected a model file") from None
    except PermissionError:
        raise InputError(f"{path}: permission denied") from None
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
        return _las_cost(Path(name), head, size)
    if suffix == ".pcd":
        return _pcd_cost(Path(name), head, size)
    if suffix == ".splat":   # 32-byte records, nothing else
        points = max(size // 32, 1)
        return FileCost(points, size, 96, 3 * size + 96 * points)
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
    _check_ply_counts(path, header, body)
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


def _check_ply_counts(path: Path, header, body: int) -> None:
    """The PLY reader's size check, on the header it parsed: the declared rows (lists empty,
    one-character ascii tokens) must fit in the body, else one FormatError line."""
    import numpy as np

    needed = 0
    for name, count, props in header.elements:
        row = (2 * len(props) if header.text else
               sum(np.dtype(p.len_dtype if p.is_list else p.dtype).itemsize for p in props))
        needed += count * row
        if needed > body + (1 if header.text else 0):
            raise FormatError(
                f"{path}: the header declares more data than the file holds: element '{name}' "
                f"({count} rows) needs at least {needed} body bytes up to its end, the body has "
                f"{body} (file cut short, or the header's count is wrong)")


#: lazrs's parallel decompressor (the whole-file load) holds decompressed LAZ chunks beside the
#: points asked for, and the compressed bytes it read: per chunk point, about this many records
#: (measured: a 3M-point LAZ written as one chunk, 30-byte records, 67 MB compressed, read 12,000
#: points at a time, peaked 276 MB above the interpreter: 67 MB + 2.3 x 90 MB).
LAZ_PARALLEL_COPIES = 2.5


def laz_reader_bytes(compressed_bytes: int, chunk_points: int, record: int,
                     parallel: bool = False) -> int:
    """What a LAZ reader holds besides the rows it returns: the sequential decompressor (the
    streamed reads) one compressed chunk (at most the whole compressed point data, at most
    ``chunk_points`` raw records when the chunk size is known); the parallel one (a whole load)
    also the decompressed chunks (:data:`LAZ_PARALLEL_COPIES`)."""
    chunk_bytes = compressed_bytes if chunk_points <= 0 else \
        min(compressed_bytes, chunk_points * record)
    if not parallel:
        return chunk_bytes
    points = chunk_points if chunk_points > 0 else compressed_bytes * 64 // max(record, 1)
    return chunk_bytes + int(LAZ_PARALLEL_COPIES * points * record)


def _las_cost(path: Path, head: bytes, size: int) -> FileCost:
    """LAS/LAZ from the header :mod:`splatdeform.io.las_header` validated against the file size
    (the same checks ``info`` and the loader run: a corrupt VLR count or point count is one
    FormatError line here, before laspy sees the file): the point records (decompressed for
    LAZ, which holds 3-10x more points than its size suggests), their decoded columns, and for
    LAZ the decompressor's buffers (:func:`laz_reader_bytes`)."""
    from .io.las_header import check_header_bytes

    layout = check_header_bytes(path, head, size)
    points, record = layout.point_count, layout.record_length
    record_bytes = record + 24 + 8   # raw record, float64 positions, decoded attributes
    load = 3 * points * record + points * 32 + size
    reader = 0
    if layout.compressed:
        data = max(size - layout.offset_to_points, 0)
        chunk = min(layout.laz_chunk_points or points, points)
        load += laz_reader_bytes(data, chunk, record, parallel=True)
        reader = laz_reader_bytes(data, chunk, record)
    return FileCost(points, size, record_bytes, load, reader)


# Measured costs of the PCD reader beside its decoded records: the raw file, and for
# binary_compressed the LZF output buffer and its bytes copy; ascii: the split rows, a bytes
# object per value and the (N, columns) object array of value texts kept for a lossless save.
PCD_ASCII_BYTES_PER_VALUE = 120


def _pcd_cost(path: Path, head: bytes, size: int) -> FileCost:
    """PCD from :func:`splatdeform.io.pcd.parse_header` (the reader's own, which checks the
    declared POINTS / WIDTH x HEIGHT against the file size for every DATA encoding): the points
    are the header's, whatever the encoding (a binary_compressed body holds more points than
    its size suggests)."""
    from .io.pcd import parse_header

    source, _ = parse_header(path, head, size)
    points = source.width * source.height
    item = source.data.dtype.itemsize
    record_bytes = item + 48   # the records, float64 positions (and normals)
    load = size + 2 * points * item + points * 48
    if source.encoding == "binary_compressed":
        load += 2 * points * item   # the LZF output and its bytes copy
    elif source.encoding == "ascii":
        load += 2 * size + points * sum(source.counts) * PCD_ASCII_BYTES_PER_VALUE
    return FileCost(points, size, record_bytes, load)


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
    ``budget``; between 5,000 and 4,000,000. ``fixed_bytes`` includes what the reader holds
    besides its rows (:attr:`FileCost.reader_bytes`: a LAZ chunk)."""
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
