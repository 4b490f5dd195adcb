"""Hostile model files (issue 11): bounded work for tiny files that declare huge counts, refusing
FIFOs and devices, ascii values their type cannot hold, strict ``info --json``, PlayCanvas
compressed splats decoded (or named), and ``--drop-nonfinite`` keeping every vertex reference
consistent.

A hang or a memory blow-up must become a test failure, not a stuck suite: those cases run in a
subprocess under ``RLIMIT_AS``, ``RLIMIT_CPU`` and a timeout (no timing asserts).
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file

from data_tools.playcanvas import compressed_ply
from splatdeform.errors import FormatError, InputError
from splatdeform.io import load, save
from splatdeform.io.ply import model_from_source
from splatdeform.io.ply_format import read_ply

ROOT = Path(__file__).resolve().parents[1]
MEMORY_LIMIT = 768 << 20  # address space for a python + numpy process reading a tiny file
XYZ = "property float x\nproperty float y\nproperty float z\n"
FACE_LIST = "property list uchar int vertex_indices\n"


CPU_LIMIT_S = 20  # CPU seconds (not wall time): ~2 s needed; quadratic header work took 22+


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
    resource.setrlimit(resource.RLIMIT_CPU, (CPU_LIMIT_S, CPU_LIMIT_S))


def run_limited(args: list[str], cwd: Path, stdout=subprocess.PIPE) -> subprocess.CompletedProcess:
    """Run under the memory limit; a hang fails the test through the timeout."""
    return subprocess.run(args, stdout=stdout, stderr=subprocess.PIPE, text=True, cwd=cwd,
                          timeout=120, preexec_fn=_limit_memory,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})


def cli(*args: str, cwd: Path, stdout=subprocess.PIPE) -> subprocess.CompletedProcess:
    return run_limited([sys.executable, "-m", "splatdeform.cli", *map(str, args)], cwd, stdout)


def assert_one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> None:
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.splitlines()) == 1, proc.stderr
    assert proc.stderr.startswith("splatdeform: error: ") and "Traceback" not in proc.stderr
    for needle in needles:
        assert needle in proc.stderr, (needle, proc.stderr)


def binary_head(extra: str) -> bytes:
    return (f"ply\nformat binary_little_endian 1.0\nelement vertex 3\n{XYZ}{extra}"
            "end_header\n").encode()


TRIANGLE = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype="<f4").tobytes()
ONE_FACE = bytes([3]) + np.array([0, 1, 2], dtype="<i4").tobytes()
ASCII_TRIANGLE = "0 0 0\n1 0 0\n0 1 0\n"

# ---------------------------------------------------------------------------------------------
# bounded work: name -> (file bytes, text the error must contain or None for "loads")


def _many_properties(n: int, duplicate: bool) -> bytes:
    names = [f"p{i}" for i in range(n)] + (["p7"] if duplicate else [])
    props = "".join(f"property uchar {name}\n" for name in names)
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex 1\n{XYZ}{props}end_header\n"
    return head.encode() + bytes(12 + len(names))


BOUNDED = {
    # the 226-byte file: 3e8 faces declared, one present
    "faces_3e8.ply": (binary_head(f"element face 300000000\n{FACE_LIST}") + TRIANGLE + ONE_FACE,
                      "declares more data than the file holds"),
    "faces_1e12.ply": (binary_head(f"element face 1000000000000\n{FACE_LIST}") + TRIANGLE,
                       "declares more data than the file holds"),
    "vertices_1e12.ply": (binary_head("").replace(b"vertex 3", b"vertex 1000000000000")
                          + TRIANGLE, "declares more data than the file holds"),
    "ascii_faces_3e8.ply": ((f"ply\nformat ascii 1.0\nelement vertex 3\n{XYZ}element face "
                             f"300000000\n{FACE_LIST}end_header\n{ASCII_TRIANGLE}3 0 1 2\n")
                            .encode(), "declares more data than the file holds"),
    "no_properties_1e13.ply": (binary_head("element junk 10000000000000\n") + TRIANGLE,
                               "no properties"),
    "ascii_no_properties_1e13.ply": ((f"ply\nformat ascii 1.0\nelement vertex 3\n{XYZ}element "
                                      f"junk 10000000000000\nend_header\n{ASCII_TRIANGLE}")
                                     .encode(), "no properties"),
    "list_rows_1e8.ply": (binary_head(f"element face 100000000\n{FACE_LIST}") + TRIANGLE
                          + bytes(64), "declares more data than the file holds"),
    "count_digits.ply": (binary_head("").replace(b"vertex 3", b"vertex " + b"9" * 5000)
                         + TRIANGLE, "too large"),
    "properties_40k.ply": (_many_properties(40_000, duplicate=False), None),
    "properties_40k_duplicate.ply": (_many_properties(40_000, duplicate=True),
                                     "duplicate property 'p7'"),
}

_PROBE = """
import json, sys
from splatdeform.io import load
out = {}
for path in sys.argv[1:]:
    try:
        model = load(path)
        out[path] = ["ok", model.n_points]
    except Exception as exc:
        out[path] = [type(exc).__name__, str(exc)]
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def bounded_results(tmp_path_factory) -> dict[str, list]:
    """Every BOUNDED file through ``load`` in one memory-limited subprocess."""
    folder = tmp_path_factory.mktemp("bounded")
    for name, (raw, _) in BOUNDED.items():
        (folder / name).write_bytes(raw)
    proc = run_limited([sys.executable, "-c", _PROBE, *BOUNDED], folder)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout)


@pytest.mark.parametrize("name", list(BOUNDED))
def test_declared_sizes_bounded(name: str, bounded_results) -> None:
    raw, expected = BOUNDED[name]
    kind, detail = bounded_results[name]
    if expected is None:
        assert kind == "ok" and detail == 1
    else:
        assert kind == "FormatError", (kind, detail)
        assert name in detail and expected in detail
        assert "\n" not in detail


def test_cli_tiny_file_huge_count_one_line(tmp_path: Path) -> None:
    path = tmp_path / "faces_3e8.ply"
    path.write_bytes(BOUNDED["faces_3e8.ply"][0])
    assert len(path.read_bytes()) == 226
    assert_one_line_error(cli("info", path, cwd=tmp_path), "faces_3e8.ply", "300000000")


def test_binary_negative_list_length(tmp_path: Path) -> None:
    head = binary_head("element face 1\nproperty list char int vertex_indices\n")
    path = tmp_path / "neglist.ply"
    path.write_bytes(head + TRIANGLE + bytes([255]) + bytes(12))  # length -1
    with pytest.raises(FormatError, match=r"neglist\.ply.*negative length"):
        load(path)


# ---------------------------------------------------------------------------------------------
# non-regular input files


def test_fifo_and_device_refused(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    zero = tmp_path / "zero.ply"
    zero.symlink_to("/dev/zero")
    # load() and the raw PLY reader both refuse (in a subprocess: a regression would block)
    probe = ("import sys\nfrom splatdeform.io import load\nfrom splatdeform.io.ply_format "
             "import read_ply\nfor f in (load, read_ply):\n    for p in sys.argv[1:]:\n"
             "        try:\n            f(p)\n        except Exception as exc:\n"
             "            print(type(exc).__name__, exc)\n")
    proc = run_limited([sys.executable, "-c", probe, str(fifo), str(zero)], tmp_path)
    lines = proc.stdout.splitlines()
    assert proc.returncode == 0 and len(lines) == 4, proc.stderr
    for line, what in zip(lines, ["named pipe", "character device"] * 2, strict=True):
        assert line.startswith("InputError") and what in line, line
    assert_one_line_error(cli("info", fifo, cwd=tmp_path), "pipe.ply", "named pipe (FIFO)")
    assert_one_line_error(cli("info", zero, cwd=tmp_path), "zero.ply", "character device")


# ---------------------------------------------------------------------------------------------
# ascii values the property type cannot hold


def _ascii_file(vertex_rows: list[str], face_rows: list[str]) -> str:
    head = ("ply\nformat ascii 1.0\ncomment hostile values\n"
            f"element vertex {len(vertex_rows)}\n{XYZ}property uchar red\nproperty uint flags\n"
            f"element face {len(face_rows)}\n{FACE_LIST}end_header\n")
    return head + "".join(r + "\n" for r in vertex_rows) + "".join(r + "\n" for r in face_rows)


GOOD_V = ["0 0 0 10 1", "1 0 0 20 2", "0 1 0 30 3", "0 0 1 40 4"]
GOOD_F = ["3 0 1 2", "3 0 2 3"]
# name -> (vertex rows, face rows, the offending token, words the message must hold)
BAD_VALUES = {
    "uchar_300": (GOOD_V[:2] + ["0 1 0 300 3"] + GOOD_V[3:], GOOD_F, "300", "0..255"),
    "uchar_minus_1": (GOOD_V[:1] + ["1 0 0 -1 2"] + GOOD_V[2:], GOOD_F, "-1", "0..255"),
    "uint_minus_1": (GOOD_V[:3] + ["0 0 1 40 -1"], GOOD_F, "-1", "0..4294967295"),
    "face_index_1_9": (GOOD_V, ["3 0 1 2", "3 0 1.9 3"], "1.9", "integer"),
    "underscore": (GOOD_V[:1] + ["1 0 0 20 1_000"] + GOOD_V[2:], GOOD_F, "1_000", "'_'"),
    "nan_in_uchar": (GOOD_V[:1] + ["1 0 0 nan 2"] + GOOD_V[2:], GOOD_F, "nan", "0..255"),
    "float_overflow": (GOOD_V[:1] + ["1 0 1e39 20 2"] + GOOD_V[2:], GOOD_F, "1e39", "float"),
    "negative_list_length": (GOOD_V, ["3 0 1 2", "-1 0 1 2"], "-1", "list length"),
    # a ragged face element (a quad) takes the per-row path; same checks there
    "ragged_face_index_1_9": (GOOD_V, ["4 0 1 2 3", "3 0 1.9 3"], "1.9", "integer"),
    "ragged_uchar_300": (GOOD_V[:3] + ["0 0 1 300 4 9"], GOOD_F, "300", "0..255"),
}


@pytest.mark.parametrize("blank_lines", [False, True])
@pytest.mark.parametrize("case", list(BAD_VALUES))
def test_ascii_value_out_of_type_rejected_with_line(case: str, blank_lines: bool,
                                                   tmp_path: Path) -> None:
    vertex_rows, face_rows, token, words = BAD_VALUES[case]
    text = _ascii_file(vertex_rows, face_rows)
    if blank_lines:  # blank lines in the body must not shift the reported line number
        head, body = text.split("end_header\n")
        text = head + "end_header\n\n" + body.replace("\n", "\n\n", 2)
    path = tmp_path / f"{case}.ply"
    path.write_text(text)
    lines = text.splitlines()
    expected_line = 1 + next(i for i, ln in enumerate(lines)
                             if i > lines.index("end_header") and token in ln.split())
    with pytest.raises(FormatError) as info:
        load(path)
    message = str(info.value)
    assert f"{case}.ply" in message and f"line {expected_line}" in message, message
    assert words in message, message


def test_ascii_good_values_read_exactly(tmp_path: Path) -> None:
    path = tmp_path / "good.ply"
    path.write_text(_ascii_file(GOOD_V[:3] + ["0 0 1 255 4294967295"], GOOD_F))
    vertex = load(path).source.element("vertex").data
    assert vertex["red"].tolist() == [10, 20, 30, 255]
    assert vertex["flags"].tolist() == [1, 2, 3, 4294967295]


def test_comment_mentioning_end_header(tmp_path: Path) -> None:
    text = _ascii_file(GOOD_V, GOOD_F).replace(
        "comment hostile values\n", "comment everything after end_header is data\n")
    path = tmp_path / "comment.ply"
    path.write_text(text)
    model = load(path)
    assert model.n_points == 4 and model.n_faces == 2
    assert "everything after end_header is data" in model.source.comments
    again = load(save(model, tmp_path / "copy.ply"))
    assert again.source.comments == model.source.comments


# ---------------------------------------------------------------------------------------------
# info --json


def _nan_normals_file(tmp_path: Path) -> Path:
    path = tmp_path / "nan_normals.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\n" + XYZ
                    + "property float nx\nproperty float ny\nproperty float nz\n"
                    + "property float radius\nend_header\n"
                    + "0 0 0 0 0 1 nan\n1 0 0 nan 0 1 inf\n0 1 0 0 0 1 -inf\n")
    return path


def test_info_json_is_strict_json(tmp_path: Path) -> None:
    path = _nan_normals_file(tmp_path)
    proc = cli("info", path, "--json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr

    def refuse(constant: str) -> None:
        raise AssertionError(f"non-JSON constant {constant} in info --json")

    info = json.loads(proc.stdout, parse_constant=refuse)
    assert info["points"] == 3
    assert None in info["normal_length_range"]


def test_info_json_closed_pipe_no_traceback(tmp_path: Path) -> None:
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader (``| head -1``) is already gone
    try:
        proc = cli("info", _nan_normals_file(tmp_path), "--json", cwd=tmp_path, stdout=write_end)
    finally:
        os.close(write_end)
    assert "Traceback" not in proc.stderr and "BrokenPipeError" not in proc.stderr, proc.stderr
    assert proc.returncode in (0, 141), proc.stderr


# ---------------------------------------------------------------------------------------------
# PlayCanvas compressed splats


def test_playcanvas_compressed_unknown_variant_named(tmp_path: Path) -> None:
    """A packed vertex element whose chunk lacks the scale bounds: named, not 'lacks x'."""
    chunk_props = "".join(f"property float {k}_{a}\n" for k in ("min", "max")
                          for a in ("x", "y", "z"))
    head = ("ply\nformat binary_little_endian 1.0\ncomment generated by splat-transform\n"
            f"element chunk 1\n{chunk_props}element vertex 2\nproperty uint packed_position\n"
            "property uint packed_rotation\nproperty uint packed_scale\n"
            "property uint packed_color\nend_header\n")
    path = tmp_path / "scene.compressed.ply"
    path.write_bytes(head.encode() + bytes(6 * 4) + bytes(2 * 16))
    with pytest.raises(FormatError, match=r"scene\.compressed\.ply.*PlayCanvas.*min_scale_x.*"
                       "not supported"):
        load(path)
    assert_one_line_error(cli("info", path, cwd=tmp_path), "PlayCanvas", "not supported")


def _compressed(model, n: int, path: Path) -> Path:
    g = model.gaussians
    rest = None if g.sh_rest is None else g.sh_rest[:n].astype(np.float64)
    path.write_bytes(compressed_ply(model.positions[:n], g.scale_log[:n].astype(np.float64),
                                    g.rotation[:n].astype(np.float64),
                                    g.opacity[:n].astype(np.float64),
                                    g.sh_dc[:n].astype(np.float64), rest))
    return path


def test_playcanvas_compressed_guitar_decodes_onto_its_grid(tmp_path: Path) -> None:
    """The shared guitar splats were decoded from a PlayCanvas compressed file, so their values
    lie on that format's quantisation grid: packing whole chunks of them and reading the file
    back gives the same scales, rotations, colours and opacities (positions within one step)."""
    guitar = load(shared_file("splats/guitar_3dgs_sh0.ply"))
    n = 512
    model = load(_compressed(guitar, n, tmp_path / "guitar.compressed.ply"))
    g, h = guitar.gaussians, model.gaussians
    assert model.kind == "gaussians" and model.n_points == n
    np.testing.assert_allclose(h.scale_log, g.scale_log[:n], atol=1e-5)
    np.testing.assert_allclose(h.sh_dc, g.sh_dc[:n], atol=1e-5)
    # byte 255 is alpha 1 (a +inf logit) as the reference decoder reads it; the shared file
    # was decoded by one that stopped short of 1, so those splats hold its largest logit
    full = np.isinf(h.opacity)
    np.testing.assert_allclose(h.opacity[~full], g.opacity[:n][~full], atol=1e-4)
    assert (h.opacity[full] > 0).all() and (g.opacity[:n][full] >= g.opacity[:n].max() - 1e-4).all()
    unit = g.rotation[:n] / np.linalg.norm(g.rotation[:n], axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs((h.rotation * unit).sum(axis=1)), 1, atol=1e-5)
    for start in range(0, n, 256):
        chunk = slice(start, min(start + 256, n))
        step = np.ptp(guitar.positions[chunk], axis=0) / np.array([2047, 1023, 2047])
        assert (np.abs(model.positions[chunk] - guitar.positions[chunk]) <= step + 1e-6).all()


def test_playcanvas_compressed_sh3_round_trip(tmp_path: Path) -> None:
    """A degree-3 tile packed with its sh element: every decoded field within half a
    quantisation step; a save writes a plain 3DGS PLY that loads back unchanged."""
    tile = load(shared_file("splats/tile_3dgs_sh3.ply"))
    n = 700
    model = load(_compressed(tile, n, tmp_path / "tile.compressed.ply"))
    g, h = tile.gaussians, model.gaussians
    assert h.sh_rest.shape == (n, 45)
    assert np.abs(h.sh_rest - np.clip(g.sh_rest[:n], -4, 4 - 8 / 256)).max() <= 8 / 256 + 1e-6
    unit = g.rotation[:n] / np.linalg.norm(g.rotation[:n], axis=1, keepdims=True)
    assert np.abs((h.rotation * unit).sum(axis=1)).min() > 1 - 1e-5  # 10-bit components
    for start in range(0, n, 256):
        chunk = slice(start, min(start + 256, n))
        half = np.ptp(tile.positions[chunk], axis=0) / np.array([2047, 1023, 2047]) / 2
        assert (np.abs(model.positions[chunk] - tile.positions[chunk]) <= half + 1e-6).all()
        half = np.ptp(g.scale_log[chunk], axis=0) / np.array([2047, 1023, 2047]) / 2
        assert (np.abs(h.scale_log[chunk] - g.scale_log[chunk]) <= half + 1e-5).all()
    saved = load(save(model, tmp_path / "tile_plain.ply"))
    assert "packed_position" not in saved.source.element("vertex").data.dtype.names
    np.testing.assert_array_equal(saved.positions, model.positions)
    np.testing.assert_array_equal(saved.gaussians.sh_rest, h.sh_rest)


def test_playcanvas_compressed_too_few_chunks(tmp_path: Path) -> None:
    path = _compressed(load(shared_file("splats/guitar_3dgs_sh0.ply")), 300,
                       tmp_path / "few.compressed.ply")
    raw = path.read_bytes()
    body = raw.index(b"end_header\n") + len(b"end_header\n")
    chunk_bytes = 18 * 4  # drop the second chunk row, keep every splat
    raw = raw[:body] + raw[body: body + chunk_bytes] + raw[body + 2 * chunk_bytes:]
    path.write_bytes(raw.replace(b"element chunk 2\n", b"element chunk 1\n", 1))
    with pytest.raises(FormatError, match=r"few\.compressed\.ply.*300 splats need 2 chunks"):
        load(path)


# ---------------------------------------------------------------------------------------------
# --drop-nonfinite keeps other elements' vertex references consistent


def _scanner_file(tmp_path: Path) -> Path:
    """5 vertices (1 and 3 NaN), a 2x3 range_grid (cells list 0 or 1 vertex), two faces and
    three edges."""
    text = ("ply\nformat ascii 1.0\nobj_info num_cols 3\nobj_info num_rows 2\n"
            f"element vertex 5\n{XYZ}element range_grid 6\n{FACE_LIST}"
            f"element face 2\n{FACE_LIST}"
            "element edge 3\nproperty int vertex1\nproperty int vertex2\nend_header\n"
            "0 0 0\nnan 0 0\n0 1 0\n1 1 nan\n2 2 0\n"
            "1 0\n0\n1 1\n1 2\n1 3\n1 4\n"
            "3 0 2 4\n3 0 1 2\n"
            "0 2\n2 3\n4 0\n")
    path = tmp_path / "scanner.ply"
    path.write_text(text)
    return path


def test_drop_nonfinite_remaps_range_grid_faces_edges(tmp_path: Path) -> None:
    path = _scanner_file(tmp_path)
    with pytest.raises(InputError, match="--drop-nonfinite"):
        load(path)
    original = read_ply(path).element("vertex").data
    model = load(path, drop_nonfinite=True)
    old_of_new = [0, 2, 4]
    np.testing.assert_array_equal(model.positions[:, 0], original["x"][old_of_new])

    def old(i: int) -> int:  # new vertex index -> old index
        return old_of_new[i]

    grid = model.source.element("range_grid")
    assert grid.count == 6  # the grid keeps its shape
    cells = [[old(i) for i in cell] for cell in grid.data["vertex_indices"]]
    assert cells == [[0], [], [], [2], [], [4]]
    faces = [[old(i) for i in f] for f in model.source.element("face").data["vertex_indices"]]
    assert faces == [[0, 2, 4]]
    np.testing.assert_array_equal(model.faces, [[0, 1, 2]])
    edges = model.source.element("edge").data
    assert [(old(a), old(b)) for a, b in zip(edges["vertex1"], edges["vertex2"],
                                              strict=True)] == [(0, 2), (4, 0)]
    # a save writes a consistent file that loads again without the flag
    again = load(save(model, tmp_path / "clean.ply"))
    assert again.source.element("range_grid").count == 6
    np.testing.assert_array_equal(again.positions, model.positions)


def test_drop_nonfinite_cli_range_grid(tmp_path: Path) -> None:
    proc = cli("info", _scanner_file(tmp_path), "--drop-nonfinite", "--json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    counts = {el["name"]: el["count"] for el in info["elements"]}
    assert counts == {"vertex": 3, "range_grid": 6, "face": 1, "edge": 2}


def _oriented(tris: np.ndarray) -> set[tuple[int, int, int]]:
    """Triangles as a set, each rotated to start at its smallest index (winding kept)."""
    out = set()
    for t in np.asarray(tris).tolist():
        k = t.index(min(t))
        out.add(tuple(t[k:] + t[:k]))
    return out


@pytest.mark.parametrize("removed", [[5], [6], [0, 9], [3, 4], [12, 13, 2]])
def test_drop_nonfinite_tristrips_keeps_other_triangles(removed: list[int],
                                                       tmp_path: Path) -> None:
    """Dropping vertices from a tristrips model loses exactly the triangles using them, with
    the winding of every other triangle unchanged (odd and even cut positions)."""
    rng = np.random.default_rng(len(removed))
    n = 16
    xyz = rng.normal(size=(n, 3)).round(3)
    strips = [list(range(0, 10)), [-1], list(range(8, 16))]
    flat = [i for part in strips for i in part]
    text = ("ply\nformat ascii 1.0\nelement vertex 16\n" + XYZ
            + "element tristrips 1\nproperty list int int vertex_indices\nend_header\n"
            + "".join(f"{a} {b} {c}\n" for a, b, c in xyz)
            + f"{len(flat)} " + " ".join(map(str, flat)) + "\n")
    path = tmp_path / "strips.ply"
    path.write_text(text)
    full = load(path)
    source = read_ply(path)
    source.element("vertex").data["y"][removed] = np.nan
    model = model_from_source(source, path, drop_nonfinite=True)
    bad = np.zeros(n, dtype=bool)
    bad[removed] = True
    remap = np.cumsum(~bad) - 1
    expected = [t for t in full.faces if not bad[t].any()]
    assert _oriented(model.faces) == _oriented(remap[np.asarray(expected)].reshape(-1, 3))
    assert model.n_faces == len(expected)


def test_drop_nonfinite_igea_tristrips(tmp_path: Path) -> None:
    path = shared_file("edge_cases/igea_tristrips.ply")
    full = load(path)
    source = read_ply(path)
    vertex = source.element("vertex").data
    rng = np.random.default_rng(3)
    removed = rng.choice(len(vertex), 300, replace=False)
    vertex["x"][removed] = np.inf
    model = model_from_source(source, path, drop_nonfinite=True)
    bad = np.zeros(len(vertex), dtype=bool)
    bad[removed] = True
    keep = ~bad[full.faces].any(axis=1)
    expected = (np.cumsum(~bad) - 1)[full.faces[keep]]
    assert model.n_points == len(vertex) - 300 and model.n_faces == int(keep.sum())
    assert _oriented(model.faces) == _oriented(expected)


def test_ragged_lists_ascii_and_binary_agree(tmp_path: Path) -> None:
    """Polygons of mixed sizes (the per-element vectorised ascii path and the binary per-row
    path) read the same lists, and fan-triangulate as (f0, fi, fi+1)."""
    rng = np.random.default_rng(7)
    polygons = [rng.integers(0, 20, size=k).tolist() for k in rng.integers(3, 7, size=40)]
    xyz = rng.normal(size=(20, 3)).round(3)
    head = (f"element vertex 20\n{XYZ}property uchar flag\nelement face {len(polygons)}\n"
            f"property uchar kind\n{FACE_LIST}property short tag\nend_header\n")
    ascii_body = "".join(f"{a} {b} {c} {i % 7}\n" for i, (a, b, c) in enumerate(xyz))
    ascii_body += "".join(f"{i % 3} {len(p)} {' '.join(map(str, p))} {-i}\n"
                          for i, p in enumerate(polygons))
    (tmp_path / "a.ply").write_text("ply\nformat ascii 1.0\n" + head + ascii_body)
    vrec = np.empty(20, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("flag", "u1")])
    for i, axis in enumerate("xyz"):
        vrec[axis] = xyz[:, i]
    vrec["flag"] = np.arange(20) % 7
    body = vrec.tobytes() + b"".join(
        bytes([i % 3, len(p)]) + np.asarray(p, dtype=">i4").tobytes()
        + np.asarray(-i, dtype=">i2").tobytes() for i, p in enumerate(polygons))
    (tmp_path / "b.ply").write_bytes(f"ply\nformat binary_big_endian 1.0\n{head}".encode()
                                     + body)
    a, b = load(tmp_path / "a.ply"), load(tmp_path / "b.ply")
    for model in (a, b):
        face = model.source.element("face").data
        assert [f.tolist() for f in face["vertex_indices"]] == polygons
        assert face["tag"].tolist() == [-i for i in range(len(polygons))]
        assert face["kind"].tolist() == [i % 3 for i in range(len(polygons))]
        fans = [(p[0], p[i], p[i + 1]) for p in polygons for i in range(1, len(p) - 1)]
        np.testing.assert_array_equal(model.faces, fans)
    np.testing.assert_array_equal(a.positions, b.positions)


@pytest.mark.parametrize("ragged", [False, True])
def test_header_plus_zeros_list_body_memory_bounded(ragged: bool, tmp_path: Path) -> None:
    """A header and a body of zeros read as a list element of empty rows (the 'header plus
    zeros' archive member): memory stays a small multiple of the file size."""
    import tracemalloc

    rows = 400_000
    body = bytearray(rows)
    if ragged:  # a few non-empty rows force the variable-length path
        body[-5:] = bytes([1, 7, 0, 0, 0])  # one row of 5 bytes instead of five of 1
        rows -= 4
    path = tmp_path / "zeros.ply"
    path.write_bytes(binary_head(f"element junk {rows}\nproperty list uchar int idx\n")
                     + TRIANGLE + bytes(body))
    size = path.stat().st_size
    tracemalloc.start()
    try:
        source = load(path).source
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    junk = source.element("junk").data["idx"]
    assert len(junk) == rows and sum(len(r) for r in junk) == (1 if ragged else 0)
    # one byte a row in the file; in memory an 8-byte object pointer, and while reading a few
    # int64 offsets/lengths a row (the fixed-length path needs ~17x, the variable one ~50x)
    assert peak < 64 * size, peak / size
