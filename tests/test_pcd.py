"""PCD read and write by our own module: every field kept through an edit, the same DATA
encoding, header fields validated against each other and the file size; Open3D (an independent
implementation, with real LZF compression) as the oracle for x y z, normals and colours."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from splatdeform.errors import FormatError
from splatdeform.io import load, pcd, save

ENCODINGS = {"ascii": dict(write_ascii=True), "binary": dict(write_ascii=False, compressed=False),
             "binary_compressed": dict(write_ascii=False, compressed=True)}


def _open3d_file(path: Path, encoding: str, n: int = 400, seed: int = 0):
    rng = np.random.default_rng(seed)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.normal(size=(n, 3))))
    cloud.normals = o3d.utility.Vector3dVector(rng.normal(size=(n, 3)))
    cloud.colors = o3d.utility.Vector3dVector(rng.uniform(size=(n, 3)))
    assert o3d.io.write_point_cloud(str(path), cloud, **ENCODINGS[encoding])
    return cloud


def _pcl_style(path: Path, encoding: str, n: int = 300, seed: int = 1) -> pcd.PcdSource:
    """A PCD with the fields PCL users keep (intensity, label, curvature, a COUNT 3 field)."""
    rng = np.random.default_rng(seed)
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                      ("label", "<u4"), ("curvature", "<f8"), ("ring", "<u2"),
                      ("hist", "<f4", (3,))])
    data = np.empty(n, dtype=dtype)
    for name in ("x", "y", "z", "intensity"):
        data[name] = np.round(rng.normal(size=n), 4)
    data["label"] = rng.integers(0, 2**32 - 1, n)
    data["curvature"] = rng.uniform(size=n)
    data["ring"] = rng.integers(0, 64, n)
    data["hist"] = np.round(rng.uniform(size=(n, 3)), 3)
    source = pcd.PcdSource(header=[("#", ".PCD v0.7"), ("VERSION", "0.7")],
                           fields=list(dtype.names), sizes=[4, 4, 4, 4, 4, 8, 2, 4],
                           types=["F", "F", "F", "F", "U", "F", "U", "F"],
                           counts=[1, 1, 1, 1, 1, 1, 1, 3], width=n // 10, height=10,
                           encoding=encoding, data=data)
    with open(path, "wb") as f:
        pcd.write_source(source, f)
    return source


@pytest.mark.parametrize("encoding", list(ENCODINGS))
def test_open3d_files_read_and_ours_read_by_open3d(tmp_path, encoding):
    cloud = _open3d_file(tmp_path / "in.pcd", encoding)
    model = load(tmp_path / "in.pcd")
    assert model.source.encoding == encoding and model.kind == "oriented_cloud"
    np.testing.assert_allclose(model.positions, np.asarray(cloud.points), atol=2e-7)
    np.testing.assert_allclose(model.normals, np.asarray(cloud.normals), atol=2e-7)
    assert np.abs(model.colors - np.asarray(cloud.colors) * 255).max() <= 0.5 + 1e-6
    model.positions[:50] += [0.5, -1, 2]
    save(model, tmp_path / "out.pcd")
    assert pcd.read_source(tmp_path / "out.pcd")[0].encoding == encoding
    back = o3d.io.read_point_cloud(str(tmp_path / "out.pcd"))
    np.testing.assert_allclose(np.asarray(back.points), model.positions, atol=1e-6)
    np.testing.assert_allclose(np.asarray(back.colors), np.asarray(cloud.colors), atol=0.5 / 255)


@pytest.mark.parametrize("encoding", list(ENCODINGS))
def test_every_field_kept_through_an_edit(tmp_path, encoding):
    original = _pcl_style(tmp_path / "in.pcd", encoding)
    model = load(tmp_path / "in.pcd")
    assert model.n_points == 300
    model.positions[::3] *= 2
    save(model, tmp_path / "out.pcd")
    src, _ = pcd.read_source(tmp_path / "out.pcd")
    assert (src.fields, src.sizes, src.types, src.counts, src.encoding) == (
        original.fields, original.sizes, original.types, original.counts, encoding)
    assert (src.width, src.height) == (30, 10)
    for name in original.fields:
        if name not in "xyz":
            np.testing.assert_array_equal(src.data[name], original.data[name])
    np.testing.assert_allclose(np.stack([src.data[a] for a in "xyz"], axis=1), model.positions,
                               rtol=1e-6, atol=1e-6)


def test_ascii_keeps_the_text_of_unchanged_values(tmp_path):
    _pcl_style(tmp_path / "in.pcd", "ascii")
    model = load(tmp_path / "in.pcd")
    model.positions[0, 0] += 0.25
    save(model, tmp_path / "out.pcd")
    before = (tmp_path / "in.pcd").read_text().splitlines()
    after = (tmp_path / "out.pcd").read_text().splitlines()
    assert len(before) == len(after)
    changed = [i for i, (a, b) in enumerate(zip(before, after, strict=True)) if a != b]
    assert len(changed) == 1
    a, b = before[changed[0]].split(), after[changed[0]].split()
    assert a[1:] == b[1:] and float(b[0]) == np.float32(float(a[0]) + 0.25)


def _header(points="POINTS 2", **over) -> bytes:
    lines = {"VERSION": "VERSION 0.7", "FIELDS": "FIELDS x y z", "SIZE": "SIZE 4 4 4",
             "TYPE": "TYPE F F F", "COUNT": "COUNT 1 1 1", "WIDTH": "WIDTH 2",
             "HEIGHT": "HEIGHT 1", "POINTS": points, "DATA": "DATA binary"}
    lines.update(over)
    return ("\n".join(v for v in lines.values() if v) + "\n").encode()


@pytest.mark.parametrize("over, message", [
    (dict(SIZE="SIZE 4 4"), "SIZE has 2 entries for 3 FIELDS"),
    (dict(TYPE="TYPE F F Q"), "TYPE Q SIZE 4 is not valid"),
    (dict(SIZE="SIZE 4 4 2"), "TYPE F SIZE 2 is not valid"),
    (dict(COUNT="COUNT 1 0 1"), "COUNT values must be >= 1"),
    (dict(WIDTH="WIDTH 3"), r"WIDTH 3 x HEIGHT 1 != POINTS 2"),
    (dict(DATA="DATA lzma"), "DATA 'lzma'"),
    (dict(FIELDS="FIELDS x y y"), "FIELDS must be distinct"),
    (dict(FIELDS="FIELDS a b c"), "lack x, y or z"),
    (dict(POINTS=""), "lacks POINTS"),
])
def test_header_faults_are_one_line(tmp_path, over, message):
    path = tmp_path / "bad.pcd"
    path.write_bytes(_header(**over) + b"\0" * 24)
    with pytest.raises(FormatError, match=message):
        load(path)


def test_huge_declared_count_is_refused_from_the_header(tmp_path):
    path = tmp_path / "huge.pcd"
    for data in ("binary", "ascii", "binary_compressed"):
        n = 4_000_000_000
        path.write_bytes(_header(f"POINTS {n}", WIDTH=f"WIDTH {n}", DATA=f"DATA {data}")
                         + (b"\0" * 8 if data == "binary_compressed" else b"1 2 3\n"))
        start = time.process_time()
        with pytest.raises(FormatError, match="huge.pcd"):
            load(path)
        assert time.process_time() - start < 5


def test_corrupt_compressed_block_and_short_ascii(tmp_path):
    path = tmp_path / "bad.pcd"
    path.write_bytes(_header(DATA="DATA binary_compressed")
                     + np.array([4, 24], "<u4").tobytes() + b"\xff\xff\xff\xff")
    with pytest.raises(FormatError, match="binary_compressed block is corrupt"):
        load(path)
    path.write_bytes(_header(DATA="DATA ascii") + b"1 2 3\n4 5   \n")
    with pytest.raises(FormatError, match="row 1 has 2 values"):
        load(path)


def test_lzf_round_trip_and_back_references():
    raw = bytes(range(256)) * 3 + b"abc" * 100
    assert pcd.lzf_decompress("x", pcd.lzf_compress(raw), len(raw)) == raw
    # a literal 'ab' then a back-reference of length 6 at distance 2: 'abababab'
    assert pcd.lzf_decompress("x", bytes([1]) + b"ab" + bytes([4 << 5, 1]), 8) == b"abababab"


def test_pcd_to_ply_keeps_every_field(tmp_path):
    _pcl_style(tmp_path / "in.pcd", "binary")
    save(load(tmp_path / "in.pcd"), tmp_path / "out.ply")
    names = load(tmp_path / "out.ply").source.element("vertex").data.dtype.names
    assert {"intensity", "label", "curvature", "ring", "hist_0", "hist_2"} <= set(names)
