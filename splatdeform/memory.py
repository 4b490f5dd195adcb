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

from dataclasses import dataclass
from pathlib import Path

BASE_BYTES = 150 * 2**20   # interpreter + numpy + scipy + pyopencl resident (measured)

# Per point of the in-memory deform beyond the loaded model: float64 geometry and its deformed
# copy, the kNN graph (~(k+1)*16*3 bytes), basis values and Jacobians of the free points.
DEFORM_BYTES_PER_POINT = 300
KNN_BYTES_PER_NEIGHBOR = 16

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


def file_cost(path: str | Path) -> FileCost:
    """Judge ``path`` from its header and size (no body is read).

    Raises InputError/FormatError (one line naming the file) for an unreadable header."""
    path = Path(path)
    size = path.stat().st_size
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return _ply_cost(path, size)
    if suffix in (".las", ".laz"):
        return _las_cost(path, size)
    points = max(size // 12, 1)
    return FileCost(points, size, 24, 4 * size + 48 * points)


def _ply_cost(path: Path, size: int) -> FileCost:
    import numpy as np

    from .io.ply_format import MAX_HEADER_BYTES, parse_header

    with open(path, "rb") as fh:
        head = fh.read(MAX_HEADER_BYTES + 4096)
    header = parse_header(path, head)
    points = sum(count for el, count, _ in header.elements if el == "vertex")
    record = 0
    for el, _, props in header.elements:
        if el == "vertex":
            record = sum(np.dtype(p.dtype).itemsize for p in props if not p.is_list)
    record = max(record, 12) + 24   # float64 positions beside the stored columns
    factor = 12 if header.text else 3   # parsed tokens / list rows; binary: buffer + columns
    return FileCost(points, size, record, max(factor * size, 2 * size + points * record))


def _las_cost(path: Path, size: int) -> FileCost:
    import io

    with open(path, "rb") as fh:
        head = fh.read(64 * 1024)
    try:
        import laspy

        header = laspy.LasHeader.read_from(io.BytesIO(head))
        points, record = int(header.point_count), int(header.point_format.size)
    except Exception:  # noqa: BLE001 - the loader reports a bad header with its own message
        points, record = max(size // 20, 1), 20
    record_bytes = record + 24 + 8   # raw record, float64 positions, decoded attributes
    return FileCost(points, size, record_bytes, 3 * points * record + points * 32)


def deform_bytes(cost: FileCost, neighbors: int = 10) -> int:
    """Peak bytes of the in-memory ``deform`` of a file of this cost (above BASE_BYTES)."""
    per_point = DEFORM_BYTES_PER_POINT + KNN_BYTES_PER_NEIGHBOR * 3 * (neighbors + 1)
    return cost.load_bytes + cost.points * (per_point + cost.record_bytes)


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
