"""PCD ``binary_compressed`` written with real LZF compression (issue 34 item 5): PCL's own
compressed PCD edited and written back compressed at no more than 1.05x its size, every field
kept, read by Open3D and by our reader; a compressed output on request (``--pcd-data``)."""

from __future__ import annotations

import io
import os

import numpy as np
import open3d as o3d
import pytest
from conftest import shared_file

from splatdeform.cli import main
from splatdeform.errors import FormatError
from splatdeform.io import load, pcd

OSD = "pcd/osd_learn0_organized.pcd"


def _data_line(path) -> bytes:
    head = path.read_bytes()[:2048]
    return next(ln for ln in head.split(b"\n") if ln.startswith(b"DATA"))


def test_pcl_file_written_back_whole_is_no_bigger():
    src = shared_file(OSD)
    source, _ = pcd.read_source(src)
    out = io.BytesIO()
    pcd.write_source(source, out)
    assert len(out.getvalue()) <= 1.05 * src.stat().st_size
    back = out.getvalue()
    header_end = back.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    packed, raw = np.frombuffer(back[header_end:header_end + 8], "<u4")
    block = pcd.lzf_decompress("x", back[header_end + 8:header_end + 8 + packed], raw)
    want = b"".join(np.ascontiguousarray(source.data[n]).tobytes() for n in source.fields)
    assert block == want   # NaN holes, labels and packed colours bit for bit


def test_pcl_file_edited_and_written_back_compressed(tmp_path):
    src = shared_file(OSD)
    out = tmp_path / "turned.pcd"
    assert main(["convert", str(src), str(out), "--drop-nonfinite",
                 "--rotate-euler=0,0,90", "--translate=0.5,0,0"]) == 0
    assert _data_line(out) == b"DATA binary_compressed"
    assert out.stat().st_size <= 1.05 * src.stat().st_size
    before, after = load(src, drop_nonfinite=True), load(out)
    assert after.source.fields == before.source.fields
    for name in before.source.fields:
        if name not in ("x", "y", "z"):
            assert np.ascontiguousarray(after.source.data[name]).tobytes() == \
                np.ascontiguousarray(before.source.data[name]).tobytes(), name
    # splat-transform's frame: +90 degrees about z, translation x sign-flipped
    x, y = before.positions[:, 0], before.positions[:, 1]
    want = np.stack([-y - 0.5, x, before.positions[:, 2]], axis=1)
    assert np.abs(after.positions - want).max() < 1e-5
    # the organized grid is kept (issue 47): Open3D, NaN cells dropped, reads the points
    cloud = o3d.io.read_point_cloud(str(out), remove_nan_points=True)
    assert len(cloud.points) == after.n_points
    assert np.allclose(np.asarray(cloud.points), after.positions, atol=1e-6)


def test_compressed_on_request_from_ply(tmp_path):
    src = shared_file("scans/bunny.ply")
    plain, packed = tmp_path / "plain.pcd", tmp_path / "packed.pcd"
    assert main(["convert", str(src), str(plain)]) == 0
    assert main(["convert", str(src), str(packed), "--pcd-data", "binary_compressed"]) == 0
    assert _data_line(plain) == b"DATA binary"
    assert _data_line(packed) == b"DATA binary_compressed"
    # float coordinates barely compress: LZF's literal runs cost 1 byte in 32 at worst
    assert packed.stat().st_size <= 1.04 * plain.stat().st_size
    a, b = load(plain), load(packed)
    assert np.array_equal(a.positions, b.positions)
    assert len(o3d.io.read_point_cloud(str(packed)).points) == a.n_points


@pytest.mark.parametrize("data", [b"", b"a", b"abcabcabcabc", bytes(100_000),
                                  bytes(range(256)) * 50, os.urandom(20_000),
                                  b"xyz" * 5000 + os.urandom(500) + b"xyz" * 5000])
def test_lzf_round_trips_and_compresses(data):
    packed = pcd.lzf_compress(data)
    assert pcd.lzf_decompress("x", packed, len(data)) == data
    if len(set(data)) < 10 and len(data) > 1000:
        assert len(packed) < len(data) / 10


def _blocks():
    """(LZF block, declared raw size) pairs: valid, declared too short or too long, corrupted
    bytes, cut short (seeded)."""
    rng = np.random.default_rng(11)
    out = []
    for raw in (b"abcabcabcabc" * 20, bytes(1000), rng.bytes(300),
                b"xyz" * 500 + rng.bytes(50)):
        packed = pcd.lzf_compress(raw)
        out += [(packed, len(raw) + d) for d in (0, 1, -1, 5, -5)]
        for _ in range(40):
            bad = bytearray(packed)
            bad[rng.integers(len(bad))] = rng.integers(256)
            out.append((bytes(bad[:rng.integers(1, len(bad) + 1)]), len(raw)))
    return out


def _outcome(decode, block, size):
    try:
        return bytes(decode("x", block, size))
    except FormatError as exc:
        return str(exc)


def test_direct_liblzf_decode_is_python_lzfs():
    """The reader's decoder (liblzf's lzf_decompress called straight into an array) gives
    python-lzf's bytes and, for a bad block, the same error line."""
    assert pcd._direct_lzf() is not None   # python-lzf's module exports liblzf's function
    kinds = set()
    for block, size in _blocks():
        want = _outcome(pcd.lzf_decompress, block, size)
        assert _outcome(pcd.lzf_decode, block, size) == want
        assert _outcome(pcd.lzf_decode, np.frombuffer(block, np.uint8), size) == want
        kinds.add(want[:70] if isinstance(want, str) else "ok")
    assert len(kinds) >= 4, kinds   # decoded, corrupt, too long and too short all met


def test_reader_without_the_direct_decoder_reads_the_same(tmp_path, monkeypatch):
    src = shared_file("scans/bunny.ply")
    packed = tmp_path / "packed.pcd"
    assert main(["convert", str(src), str(packed), "--pcd-data", "binary_compressed"]) == 0
    direct = load(packed)
    monkeypatch.setattr(pcd, "_DIRECT_LZF", [None])   # python-lzf's decompress instead
    assert pcd._direct_lzf() is None
    plain = load(packed)
    assert np.array_equal(direct.positions, plain.positions)
    assert direct.source.data.tobytes() == plain.source.data.tobytes()
