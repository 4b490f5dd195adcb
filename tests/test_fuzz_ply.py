"""Fuzzing the PLY loader: header and body mutations of small files (generated ones and slices of
the shared real files) must only ever load or raise the project's own errors, with memory bounded
relative to the file size (tracemalloc sees numpy's buffers too), and whatever loads must give
strict JSON through ``info``. Derandomized, so a failure reproduces.
"""

from __future__ import annotations

import json
import re
import tempfile
import tracemalloc
from dataclasses import replace
from io import BytesIO
from pathlib import Path

import numpy as np
import plyfile
from conftest import SHARED_DATA
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from data_tools.playcanvas import compressed_ply
from data_tools.synth import bumpy_bar
from splatdeform.errors import SplatdeformError
from splatdeform.info import describe, to_json
from splatdeform.io import load
from splatdeform.io.ply import write_model
from splatdeform.io.ply_format import read_ply, write_ply
from splatdeform.model import PlyElementData

# peak traced allocation allowed while loading a file of S bytes: a fixed allowance for the
# interpreter's own work plus a generous per-byte factor (one small array object per list row)
BASE_BYTES = 48 << 20
PER_FILE_BYTE = 400

HAND_MADE = [
    b"ply\nformat ascii 1.0\ncomment hand made\nelement vertex 4\nproperty float x\n"
    b"property float y\nproperty float z\nproperty uchar red\nproperty uchar green\n"
    b"property uchar blue\nelement face 3\nproperty list uchar int vertex_indices\nend_header\n"
    b"0 0 0 255 0 0\n1 0 0 0 255 0\n0 1 0 0 0 255\n0 0 1 9 9 9\n3 0 2 1\n4 0 1 3 2\n3 1 2 3\n",
    b"ply\nformat ascii 1.0\nelement vertex 5\nproperty double x\nproperty double y\n"
    b"property double z\nproperty float nx\nproperty float ny\nproperty float nz\n"
    b"element tristrips 1\nproperty list int int vertex_indices\nend_header\n"
    b"0 0 0 0 0 1\n1 0 0 0 0 1\n0 1 0 0 0 1\n1 1 0 0 0 1\n2 1 0 0 0 1\n6 0 1 2 3 -1 4\n",
]


def _bytes_of(source) -> bytes:
    out = BytesIO()
    write_ply(source, out)
    return out.getvalue()


def _slice(path: Path, rows: int) -> bytes:
    """A valid file of the first ``rows`` vertices of a real file: faces using later vertices
    left out, later strip vertices turned into separators, other elements cut to ``rows``."""
    source = read_ply(path)
    elements = []
    for el in source.elements:
        data = el.data[:rows].copy()
        if el.name == "face":
            keep = [bool((np.asarray(f) < rows).all()) for f in el.data["vertex_indices"]]
            data = el.data[np.array(keep, dtype=bool)][:rows].copy()
        elif el.name == "tristrips":
            strip = np.asarray(data["vertex_indices"][0])[:4 * rows]
            data["vertex_indices"][0] = np.where(strip < rows, strip, -1).astype(strip.dtype)
        elements.append(PlyElementData(el.name, el.properties, data))
    return _bytes_of(replace(source, elements=elements))


def _seeds() -> list[bytes]:
    seeds = list(HAND_MADE)
    bar = BytesIO()
    write_model(bumpy_bar(12, seed=5), bar)
    seeds.append(bar.getvalue())
    rng = np.random.default_rng(9)
    n = 20
    seeds.append(compressed_ply(rng.normal(size=(n, 3)), rng.normal(-4, 1, size=(n, 3)),
                                rng.normal(size=(n, 4)), rng.normal(size=n),
                                rng.normal(size=(n, 3)), rng.normal(size=(n, 9))))
    for rel, rows in (("splats/tile_3dgs_sh3.ply", 3), ("edge_cases/pepper_extra_elements.ply", 6),
                      ("edge_cases/horse_big_endian.ply", 8), ("scans/head_surfels.ply", 6),
                      ("edge_cases/igea_tristrips.ply", 10)):
        if SHARED_DATA.is_dir():   # a file missing from the folder fails (FileNotFoundError)
            seeds.append(_slice(SHARED_DATA / rel, rows))
    return seeds


SEEDS = _seeds()
WORDS = ["0", "1", "-1", "3", "255", "300", "1.9", "1_000", "nan", "inf", "1e39", "4294967296",
         "99999999999999", "1" * 30, "uchar", "char", "int", "uint", "float", "double", "list",
         "vertex", "face", "x", "end_header", "property", "element", "comment", "", "é"]


def _body_start(raw: bytearray) -> int:
    end = raw.find(b"end_header")
    newline = raw.find(b"\n", end) if end >= 0 else -1
    return len(raw) if newline < 0 else newline + 1


@st.composite
def mutated(draw) -> bytes:
    """A seed with 1-4 mutations: header words, lines and element counts; body tokens and
    bytes; now and then a byte anywhere (which mostly breaks the magic or the header)."""
    raw = bytearray(draw(st.sampled_from(SEEDS)))
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["word", "line", "count", "count", "token", "token",
                                     "token", "bytes", "bytes", "bytes", "anywhere"]))
        start = _body_start(raw)
        end = raw.find(b"end_header")
        if kind in ("word", "line", "count") and end > 0:
            lines = bytes(raw[:end]).split(b"\n")
            counted = [i for i, ln in enumerate(lines) if ln.startswith(b"element ")]
            if kind == "count" and counted:
                i = draw(st.sampled_from(counted))
                words = lines[i].split(b" ")
                if len(words) == 3 and words[2].isdigit():
                    delta = draw(st.sampled_from([-2, -1, 1, 2, 7, 1000, 10**9, 10**13]))
                    words[2] = str(max(int(words[2]) + delta, 0)).encode()
                    lines[i] = b" ".join(words)
            elif kind == "word":
                i = draw(st.integers(1, len(lines) - 1))
                words = lines[i].split(b" ")
                j = draw(st.integers(0, len(words) - 1))
                words[j] = draw(st.sampled_from(WORDS)).encode()
                lines[i] = b" ".join(words)
            else:
                i = draw(st.integers(1, len(lines) - 1))
                op = draw(st.sampled_from(["delete", "duplicate", "swap"]))
                if op == "delete":
                    del lines[i]
                elif op == "duplicate":
                    lines.insert(i, lines[i])
                else:
                    k = draw(st.integers(1, len(lines) - 1))
                    lines[i], lines[k] = lines[k], lines[i]
            raw[:end] = b"\n".join(lines)
            continue
        if kind == "token":
            tokens = [m.span() for m in re.finditer(rb"\S+", bytes(raw[start:]))]
            if tokens:
                a, b = tokens[draw(st.integers(0, len(tokens) - 1))]
                raw[start + a: start + b] = draw(st.sampled_from(WORDS)).encode()
            continue
        low = 0 if kind == "anywhere" else start
        if low >= len(raw):
            continue
        pos = draw(st.integers(low, len(raw) - 1))
        op = draw(st.sampled_from(["flip", "insert", "delete", "truncate", "repeat"]))
        if op == "flip":
            raw[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "insert":
            raw[pos:pos] = draw(st.sampled_from([b" ", b"\n", b"-", b"7", b".", b"\x00" * 4,
                                                 b"\xff" * 4, b" 300", b" 1_0", b"\n\n"]))
        elif op == "delete":
            del raw[pos: pos + draw(st.integers(1, 16))]
        elif op == "truncate":
            del raw[pos:]
        else:
            raw[pos:pos] = raw[pos: pos + draw(st.integers(1, 64))]
    return bytes(raw)


def _load_within_bound(path: Path, size: int) -> None:
    tracemalloc.start()
    try:
        try:
            model = load(path)
        except SplatdeformError as exc:
            assert str(path.name) in str(exc), exc
            model = None
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak <= BASE_BYTES + PER_FILE_BYTE * size, (peak, size)
    if model is not None:
        info = json.loads(to_json(describe(model)), parse_constant=lambda c: 1 / 0)
        assert info["points"] == model.n_points >= 1
        _same_as_plyfile(path, model)


def _same_values(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")


def _canonical(raw: bytes) -> bytes:
    """``raw`` without the leniencies our reader allows and plyfile does not: one ``format``
    line of version 1.0 right after ``ply`` (ours takes the first, wherever it is, and any
    version), no blank header lines, and for ASCII no blank body lines (ours reads
    whitespace-separated tokens)."""
    end = raw.index(b"end_header")
    lines = raw[:end].split(b"\n")
    fmt = next(ln.split() for ln in lines if ln.startswith(b"format"))
    rest = [ln for ln in lines[1:] if ln.strip() and not ln.startswith(b"format")]
    head = b"".join(ln + b"\n" for ln in [lines[0], b"format " + fmt[1] + b" 1.0", *rest])
    newline = raw.index(b"\n", end) + 1
    body = raw[newline:]
    if fmt[1] == b"ascii":
        body = b"".join(ln + b"\n" for ln in body.split(b"\n") if ln.strip())
    return head + raw[end:newline] + body


def _same_as_plyfile(path: Path, model) -> None:
    """A file our loader accepts is one plyfile (the independent reader) reads, once put in
    canonical form (:func:`_canonical`), to the same elements, counts, names and values; the
    loaded model's positions are plyfile's x, y, z."""
    ours = read_ply(path)
    canonical = path.with_name("canonical.ply")
    canonical.write_bytes(_canonical(path.read_bytes()))
    try:
        ref = plyfile.PlyData.read(str(canonical))
    except Exception as exc:  # noqa: BLE001 - any refusal is a disagreement
        raise AssertionError(f"our loader accepts a file plyfile refuses: {exc}") from exc
    assert [e.name for e in ours.elements] == [e.name for e in ref.elements]
    for el, rel in zip(ours.elements, ref.elements, strict=True):
        assert el.data.dtype.names == rel.data.dtype.names, el.name
        assert len(el.data) == len(rel.data), el.name
        for name in el.data.dtype.names:
            a, b = el.data[name], rel.data[name]
            if a.dtype == object:
                bad = [i for i, (x, y) in enumerate(zip(a, b, strict=True))
                       if not _same_values(np.asarray(x), np.asarray(y))]
                assert not bad, f"{el.name}.{name}: list rows {bad[:5]} differ from plyfile's"
            else:
                assert (a.dtype.kind, a.dtype.itemsize) == (b.dtype.kind, b.dtype.itemsize)
                assert _same_values(a, b.astype(a.dtype)), f"{el.name}.{name} differs"
    names = ref["vertex"].data.dtype.names if "vertex" in ref else ()
    if {"x", "y", "z"} <= set(names):
        xyz = np.column_stack([ref["vertex"].data[c].astype(np.float64) for c in "xyz"])
        assert _same_values(model.positions, xyz), "positions differ from plyfile's x, y, z"


@settings(max_examples=400, derandomize=True, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(raw=mutated())
def test_mutated_ply_only_project_errors(raw: bytes) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "fuzz.ply"
        path.write_bytes(raw)
        _load_within_bound(path, len(raw))


def test_seeds_load() -> None:
    """The unmutated seeds are valid files (so the mutations start from something real)."""
    with tempfile.TemporaryDirectory() as folder:
        for i, raw in enumerate(SEEDS):
            path = Path(folder) / f"seed{i}.ply"
            path.write_bytes(raw)
            assert load(path).n_points >= 1
    assert len(SEEDS) >= 3 and np.mean([len(s) for s in SEEDS]) < 20_000
