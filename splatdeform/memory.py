"""The one memory estimator: what loading, deforming or rendering a file will cost, judged from
its header and size before anything is read.

Every budget decision goes through here: ``deform``'s stream-or-not choice, the batch per-worker
guard, and the render budget (sample or not). The figures are peaks in bytes of resident memory
above the interpreter's own (see :data:`BASE_BYTES`), so a caller compares
``BASE_BYTES + estimate`` with its budget.

The budget policy lives here too: sizes (:func:`parse_size`), the machine's memory
(:func:`machine_memory`: the physical RAM, the one definition) and the default budget
(:func:`default_budget`, half of it; a batch worker's default is that divided among the workers
running at once, :func:`worker_budget`), the margins a run may exceed its budget by
(:data:`BUDGET_MARGIN`; a batch worker's hard cap :data:`CAP_SLACK_BYTES`), what a streamed run
sizes from its budget (:func:`stream_sizes`, :func:`sample_sizes`) and the one rule
(:func:`choose`) that decides in memory / stream / refuse for ``deform``, ``render`` (through
:func:`render_points`), ``select``, batch and the editor.

Every file an estimate reads is opened with :func:`splatdeform.io.regular.open_regular`, and
judged by its format's declared header probe (:mod:`splatdeform.io.declare`, through
:func:`splatdeform.io.header_cost`): the reader's own header parser, validated against the file
size (LAS/LAZ: :mod:`splatdeform.io.las_header`, PLY and compressed PLY:
:func:`splatdeform.io.ply_format.parse_header`, PCD: :func:`splatdeform.io.pcd.parse_header`,
SPZ: its gzip'd header, SOG: meta.json, glTF: its JSON's accessors), never a second parser that
would trust what a header claims before the checks run. The splat formats' estimates come from
the count their header declares, so an explicit budget caps them too.

A header can lie and a body can amplify: ASCII values and PLY list rows cost several times
their bytes once parsed, so the load estimate takes the larger of what the header's counts
imply and what the file's size can hold.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from .errors import ConfigError, InputError

# the estimator's figures, declared with their formats (re-exported: one place to ask)
from .io.declare.las import LAZ_PARALLEL_COPIES as LAZ_PARALLEL_COPIES
from .io.declare.las import laz_reader_bytes as laz_reader_bytes
from .io.format import HEAD_BYTES as HEAD_BYTES
from .io.format import FileCost
from .rbf.defaults import DEFAULT_MAX_CENTERS

BASE_BYTES = 150 * 2**20   # interpreter + numpy + scipy + pyopencl resident (measured)

# Per point of the in-memory deform beyond the loaded model: float64 geometry and its deformed
# copy, the kNN graph (~(k+1)*16*3 bytes); d(x) and J(x) are evaluated one-shot in chunks
# (issue 45: 1M points measured ~300 B/point above the interpreter, the load included).
DEFORM_BYTES_PER_POINT = 150
# A stored basis (--reuse, the editor): b and grad b of every point in float32, k = 4 columns
STORED_BASIS_BYTES_PER_POINT = 4 * 16 * 4
# the rings' kNN graph, per point and neighbour: 16 bytes over the border band only (the
# points with an edge: ~0.3M of a 5M bend), so counted as half the points' worth, with room
# for wide bands; the 5M bend measured ~220 B/point in all (issue 45)
KNN_BYTES_PER_NEIGHBOR = 8
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
#: B); tests/test_budget_refusals.py measures it. A render adds its GL context (see
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


def worker_budget(workers: int) -> int:
    """A batch worker's default budget (no ``memory_per_worker_mb``): the default budget
    (:func:`default_budget`, half the RAM) shared by the ``workers`` scans running at once."""
    return default_budget() // max(1, workers)


#: A batch worker process runs each scan under a hard cap (RLIMIT_DATA) of what it has mapped
#: plus its budget plus this slack, for what the estimate cannot see (see
#: :func:`splatdeform.batch.worker.cap_memory`): a scan that outgrows it fails alone.
CAP_SLACK_BYTES = 300 * 2**20

#: Bytes per point a streamed edit holds whole beside its chunks: the label byte and the
#: region pass's per-point bookkeeping (``select`` keeps the label byte only).
STREAM_LABEL_BYTES = 2

#: Render sampling: raw records read per chunk (at most; an eighth of the budget), and the
#: fewest points a sample keeps whatever the budget (a picture needs some points).
SAMPLE_CHUNK_BYTES = 64 * 2**20
MIN_SAMPLE_POINTS = 10_000


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
      ``whole`` or ``why_not`` is what keeps it there.
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
    reason = (f"{whole} needs the whole model in memory" if whole is not None else
              why_not if not streamable and why_not else "")
    warning = "" if not reason else (f"{name}: over the memory budget ({_mb(limit)}), but "
                                     f"{reason}: running in memory")
    return Choice("memory", need, limit, explicit, warning)


def file_cost(path: str | Path) -> FileCost:
    """Judge ``path`` from its header and size (no body is read), through the one opener
    (:func:`splatdeform.io.regular.open_regular`: a FIFO or a device is refused, not read) and
    its format's declared header probe (:func:`splatdeform.io.header_cost`).

    Raises InputError/FormatError (one line naming the file) for an unreadable header or one
    that declares more than the file holds."""
    from .io import header_cost
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
    return header_cost(path, head, size, file=path)


def head_cost(name: str | Path, head: bytes, size: int, suffix: str | None = None) -> FileCost:
    """:func:`file_cost` from the file's first bytes ``head`` (up to :data:`HEAD_BYTES`) and its
    ``size``: what the batch guard uses for an archive member before extracting it.
    ``suffix`` (default: the name's extension) picks the format."""
    from .io import header_cost

    return header_cost(name, head, size, suffix)


def deform_bytes(cost: FileCost, neighbors: int = 10,
                 max_centers: int = DEFAULT_MAX_CENTERS, *, stored: bool = False,
                 growth: float = 0.0) -> int:
    """Peak bytes of the in-memory ``deform`` of a file of this cost (above BASE_BYTES): the
    load, the per-point arrays, and the fit's matrices (constraint rows x centers, with the
    modules the run imports on the way; measured up to ~200 MiB at 2000 centers whatever the
    point count, see tests/test_memory.py); ``stored``: the basis is kept (``--reuse``)
    rather than evaluated one-shot; ``growth``: the most the deformed copy may grow by, as a
    fraction of the points (split splats: :data:`splatdeform.deform.split.GROWTH_CAP`)."""
    per_point = DEFORM_BYTES_PER_POINT + KNN_BYTES_PER_NEIGHBOR * 3 * (neighbors + 1) + \
        (STORED_BASIS_BYTES_PER_POINT if stored else 0)
    return cost.load_bytes + cost.points * (per_point + cost.record_bytes) + \
        int(growth * cost.points * cost.record_bytes) + FIT_BYTES_PER_CENTER * max_centers


def deform_peak(cost: FileCost, neighbors: int = 10,
                max_centers: int = DEFAULT_MAX_CENTERS, *, stored: bool = False,
                growth: float = 0.0) -> int:
    """Peak bytes of the whole process for an in-memory ``deform``: :data:`BASE_BYTES` plus
    :func:`deform_bytes` (what the stream-or-not choice and the batch guard compare)."""
    return BASE_BYTES + deform_bytes(cost, neighbors, max_centers, stored=stored, growth=growth)


#: the most points a streamed chunk holds, whatever the budget: bigger chunks run slower, their
#: arrays no longer in the CPU caches (the 5M bend of a LAZ, pass 5 on 2 cores: 231k points a
#: chunk 3.1-3.3 s, 131k 2.2 s, 65k 2.2-2.3 s, 33k 2.4-2.5 s; of the same points as PLY 1.1-1.3 s
#: at any of these; a PLY->PLY copy: 1M 0.86 s, 65k 0.45 s)
STREAM_CHUNK_MAX = 131_072


def stream_chunk(budget: int, record_bytes: int, fixed_bytes: int) -> int:
    """Points per streamed chunk so that a chunk's working set (~4 copies of a record plus
    :data:`STREAM_BYTES_PER_POINT`) takes a quarter of what ``fixed_bytes`` leaves of
    ``budget``; between 5,000 and :data:`STREAM_CHUNK_MAX`. ``fixed_bytes`` includes what the
    reader holds besides its rows (:attr:`FileCost.reader_bytes`: a LAZ chunk)."""
    left = max(budget - fixed_bytes, budget // 4)
    per_point = 4 * record_bytes + STREAM_BYTES_PER_POINT
    return int(min(max(left // 4 // per_point, 5_000), STREAM_CHUNK_MAX))


@dataclass(frozen=True)
class StreamSizes:
    """What a streamed edit holds within its budget: ``chunk`` points per chunk,
    ``max_border`` border points, ``max_handle`` handle points kept whole (beyond: streamed
    moments), and ``fixed`` the bytes held whatever the chunk (interpreter, labels, what the
    reader keeps besides its rows)."""

    chunk: int
    max_border: int
    max_handle: int
    fixed: int


def stream_sizes(budget: int, points: int, record_bytes: int, reader_bytes: int = 0
                 ) -> StreamSizes:
    """The sizes of a streamed edit of ``points`` records of ``record_bytes`` within ``budget``
    bytes (:func:`stream_chunk`, :func:`stream_caps`); ``reader_bytes``: what the reader holds
    besides its rows (:attr:`FileCost.reader_bytes`)."""
    fixed = BASE_BYTES + STREAM_LABEL_BYTES * points + reader_bytes
    border, handle = stream_caps(budget, fixed)
    return StreamSizes(stream_chunk(budget, record_bytes, fixed_bytes=fixed), border, handle,
                       fixed)


def select_chunk(budget: int, points: int, record_bytes: int) -> int:
    """Points per chunk of ``select``'s streamed regions pass (one label byte a point)."""
    return stream_chunk(budget, record_bytes, fixed_bytes=BASE_BYTES + points)


def select_preview_budget(budget: int, points: int) -> int:
    """What ``select``'s sampled preview may hold beside its labels (one byte a point)."""
    return max(budget - points, budget // 2)


def sample_sizes(limit: int, cost: FileCost) -> tuple[int, int]:
    """(bytes read per chunk, points that fit) of a render within ``limit`` bytes: all the
    file's points when it fits (:func:`render_points`, two chunks and the reader's buffers
    reserved); a sample then keeps at least :data:`MIN_SAMPLE_POINTS`."""
    chunk_bytes = min(SAMPLE_CHUNK_BYTES, limit // 8)
    return chunk_bytes, render_points(limit, cost, reserve=2 * chunk_bytes + cost.reader_bytes)


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
