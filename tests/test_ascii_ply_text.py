"""ASCII PLY: a save keeps the original text of every value that did not change and writes
the shortest round-trip text for the changed ones; an untouched file is reproduced exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splatdeform.io import load, save
from splatdeform.io.ply_format import ASCII_CHUNK_ROWS, read_ply

HEAD = """ply
format ascii 1.0
comment hand written
element vertex {n}
property float x
property float y
property float z
property uchar red
property double quality
element face {f}
property list uchar int vertex_indices
end_header
"""


def _file(path: Path, n: int) -> Path:
    rng = np.random.default_rng(4)
    rows = [f"{x:.4f} {y:.3f} {z:.5f} {c} {q:.2e}" for x, y, z, c, q in zip(
        rng.normal(size=n), rng.normal(size=n), rng.normal(size=n), rng.integers(0, 255, n),
        rng.uniform(size=n), strict=True)]
    faces = [f"3 {i} {i + 1} {i + 2}" for i in range(0, n - 2, 3)]
    path.write_text(HEAD.format(n=n, f=len(faces)) + "\n".join(rows + faces) + "\n")
    return path


def test_untouched_ascii_file_is_reproduced_byte_for_byte(tmp_path):
    src = _file(tmp_path / "in.ply", 500)
    save(load(src), tmp_path / "out.ply")
    assert (tmp_path / "out.ply").read_bytes() == src.read_bytes()


def test_only_changed_values_are_reprinted_shortest(tmp_path):
    src = _file(tmp_path / "in.ply", 300)
    model = load(src)
    model.positions[5, 1] = -0.1253
    model.positions[7] += 1.0
    save(model, tmp_path / "out.ply")
    before = src.read_text().splitlines()
    after = (tmp_path / "out.ply").read_text().splitlines()
    assert len(before) == len(after)
    diff = [i for i, (a, b) in enumerate(zip(before, after, strict=True)) if a != b]
    head = len(HEAD.splitlines())
    assert diff == [head + 5, head + 7]
    assert after[head + 5].split()[1] == "-0.1253"  # not -0.125300005
    assert after[head + 5].split()[0::2] == before[head + 5].split()[0::2]
    for a, b in zip(after[head + 7].split()[:3], before[head + 7].split()[:3], strict=True):
        assert np.float32(float(a)) == np.float32(np.float32(float(b)) + np.float32(1.0)) or \
            np.float32(float(a)) == np.float32(float(b) + 1.0)
    back = load(tmp_path / "out.ply")
    np.testing.assert_array_equal(back.positions.astype(np.float32),
                                  model.positions.astype(np.float32))


def test_chunked_parse_matches_across_chunk_boundaries(tmp_path):
    n = ASCII_CHUNK_ROWS + 17
    src = _file(tmp_path / "big.ply", n)
    source = read_ply(src)
    vertex = source.element("vertex")
    assert vertex.count == n
    lines = src.read_text().splitlines()
    head = len(HEAD.splitlines())
    for i in (0, ASCII_CHUNK_ROWS - 1, ASCII_CHUNK_ROWS, n - 1):
        x = float(lines[head + i].split()[0])
        assert vertex.data["x"][i] == np.float32(x)
