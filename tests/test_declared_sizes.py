"""Declared sizes checked before anything is allocated (issue 43 item 7): SPZ v3 and v4 headers
that declare more splats than their compressed bytes plausibly hold, a PCD LZF block that declares
more raw bytes than LZF can expand to, a ``.ksplat`` section whose partial buckets declare 300M
splats; each refused with one line naming the file and what it declared, in ``info`` and
``convert`` alike, within 300 MB of peak memory. Legal LZF back references decode at the compiled
library's speed, and an out-of-memory line names the file."""

from __future__ import annotations

import gzip
import struct
from pathlib import Path

import numpy as np
import pytest
from helpers import one_error_line, run_cli, run_cli_peak

from splatdeform.errors import FormatError
from splatdeform.io import load, pcd, spz

PEAK = 300 * 2**20


def _spz_v3(path: Path, count: int, degree: int = 3, body: bytes = bytes(1024)) -> Path:
    """A gzip'd v3 stream whose header declares ``count`` splats over ``body``."""
    head = spz.HEADER.pack(spz.MAGIC, 3, count, degree, 12, 0, 0)
    path.write_bytes(gzip.compress(head + body, mtime=0))
    return path


def _spz_v4(path: Path, count: int, packed: int = 700) -> Path:
    """A v4 file declaring ``count`` degree-0 splats whose table passes ZSTD's own ratio bound
    (``packed`` bytes of each stream, not a real ZSTD frame)."""
    per = spz.stream_bytes(0, 4)
    table = b"".join(spz.TOC_ENTRY.pack(packed, count * p) for p in per)
    head = spz.V4_HEADER.pack(spz.MAGIC, 4, count, 0, 12, 0, len(per), spz.V4_HEADER.size,
                              bytes(12))
    path.write_bytes(head + table + bytes(packed * len(per)))
    return path


def _pcd(path: Path, block: bytes, raw_size: int, points: int, fields: int = 4) -> Path:
    names = "x y z w"[:2 * fields - 1]
    head = (f"VERSION 0.7\nFIELDS {names}\nSIZE {' '.join(['4'] * fields)}\n"
            f"TYPE {' '.join(['F'] * fields)}\nCOUNT {' '.join(['1'] * fields)}\n"
            f"WIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\n"
            "DATA binary_compressed\n").encode()
    path.write_bytes(head + struct.pack("<II", len(block), raw_size) + block)
    return path


def _refused_everywhere(path: Path, tmp_path: Path, needles: tuple[str, ...]) -> None:
    """``info`` and ``convert`` both refuse ``path`` with one line, under :data:`PEAK`."""
    for args in (("info", path), ("convert", path, tmp_path / "out.ply")):
        res, peak = run_cli_peak(*args, cwd=tmp_path)
        one_error_line(res, needles=(path.name, *needles))
        assert peak < PEAK, (args[0], peak / 2**20)
    assert not (tmp_path / "out.ply").exists()


def test_spz_v3_declaring_millions_of_splats_in_a_small_file(tmp_path):
    # ~330 KB of incompressible body: within deflate's 1032x of the 325 MB declared
    body = np.random.default_rng(43).bytes(330_000)
    path = _spz_v3(tmp_path / "big_v3.spz", 5_000_000, body=body)
    assert path.stat().st_size < 400_000
    with pytest.raises(FormatError, match="5,000,000 splats"):
        load(path)
    _refused_everywhere(path, tmp_path, ("5,000,000 splats", "compresses at most"))


def test_spz_v4_declaring_millions_of_splats_in_a_small_file(tmp_path):
    path = _spz_v4(tmp_path / "big_v4.spz", 8_000_000, packed=2300)
    assert path.stat().st_size < 12_500
    with pytest.raises(FormatError, match="8,000,000 splats"):
        load(path)
    _refused_everywhere(path, tmp_path, ("8,000,000 splats", "compresses at most"))


def test_spz_within_the_bound_still_reads(tmp_path):
    """A small scene of near-identical splats (far more compressible than any real scene) is
    within the bound's slack, written and read back."""
    from splatdeform.io.splats import SplatFields

    n = 50_000
    f = SplatFields(positions=np.zeros((n, 3)), scale_log=np.full((n, 3), -3, np.float32),
                    rotation=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                    opacity=np.zeros(n, np.float32), sh_dc=np.zeros((n, 3), np.float32),
                    sh_rest=np.zeros((n, 3, 15), np.float32))
    path = tmp_path / "flat.spz"
    path.write_bytes(spz.write_v4(spz.encode(f, version=4)))
    assert path.stat().st_size * spz.PLAUSIBLE_RATIO < spz.stream_size(spz.read_info(path))
    assert load(path).n_points == n


def test_pcd_lzf_block_declaring_2_gib(tmp_path):
    # 2^27 points of 16 bytes: a raw block of 2^31 bytes from 4 compressed bytes
    path = _pcd(tmp_path / "bomb.pcd", b"\x00abc", 2**31, 2**27)
    assert path.stat().st_size < 400
    with pytest.raises(FormatError, match="LZF expands at most 88x"):
        load(path)
    _refused_everywhere(path, tmp_path, ("2,147,483,648 raw bytes",))


def _overlapping(n_refs: int) -> bytes:
    """An LZF block of one literal byte then ``n_refs`` back references of 264 bytes at
    distance 1 (each overlapping its own output): the largest legal expansion."""
    ref = bytes([(7 << 5) | 0, 264 - 2 - 7, 0])
    return bytes([0]) + b"\x01" + ref * n_refs


def test_pcd_legal_overlapping_back_references_decode(tmp_path):
    n_refs = 100_000   # 300 KB of block, 26 MB of raw bytes
    raw = 1 + 264 * n_refs
    raw -= raw % 16
    block = _overlapping(n_refs)
    # cut the last reference so that the block decodes to exactly the raw size
    out = pcd.lzf_decompress("x", block, 1 + 264 * n_refs)
    assert out == b"\x01" * (1 + 264 * n_refs)
    path = _pcd(tmp_path / "runs.pcd", pcd.lzf_compress(out[:raw]), raw, raw // 16)
    model = load(path)
    assert model.n_points == raw // 16
    res, peak = run_cli_peak("info", path, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert peak < PEAK, peak / 2**20


def test_pcd_lzf_block_that_decodes_short_or_long(tmp_path):
    block = pcd.lzf_compress(bytes(range(256)) * 4)
    with pytest.raises(FormatError, match="decodes to 1,024 bytes, its header says 2,048"):
        pcd.lzf_decompress("x", block, 2048)
    with pytest.raises(FormatError, match="corrupt"):
        pcd.lzf_decompress("x", block, 512)


KSPLAT_MAIN = struct.Struct("<BBxxIIIIH2x3f2f")
KSPLAT_SECTION = struct.Struct("<IIIIfH2xIIIIH")


def _ksplat(path: Path, count: int, partial_lengths: list[int]) -> Path:
    """A level-1 .ksplat of one section: ``count`` splats (24-byte records, degree 0), no full
    bucket, the partial buckets' lengths as given."""
    buckets = len(partial_lengths)
    main = bytearray(4096)
    KSPLAT_MAIN.pack_into(main, 0, 0, 1, 1, 1, count, count, 1, 0, 0, 0, 0, 0)
    section = bytearray(1024)
    KSPLAT_SECTION.pack_into(section, 0, count, count, 256, buckets, 1.0, 12, 0, 0, 0,
                             buckets, 0)
    lengths = np.array(partial_lengths, "<u4").tobytes()
    centers = np.zeros(3 * buckets, "<f4").tobytes()
    rng = np.random.default_rng(43)
    records = np.zeros(count, [("c", "<u2", 3), ("s", "<f2", 3), ("r", "<f2", 4),
                               ("rgba", "u1", 4)])
    records["c"] = rng.integers(0, 65535, (count, 3))
    records["s"] = 0.01
    records["r"] = [1, 0, 0, 0]
    records["rgba"] = 200
    path.write_bytes(bytes(main) + bytes(section) + lengths + centers + records.tobytes())
    return path


def test_ksplat_partial_bucket_declaring_300m_splats(tmp_path):
    path = _ksplat(tmp_path / "buckets.ksplat", 10_000, [300_000_000])
    assert path.stat().st_size < 300_000
    res, peak = run_cli_peak("convert", path, tmp_path / "out.ply", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert peak < PEAK, peak / 2**20
    assert load(tmp_path / "out.ply").n_points == 10_000


def test_ksplat_partial_buckets_assign_splats_in_order(tmp_path):
    path = _ksplat(tmp_path / "two.ksplat", 300, [100, 500])
    model = load(path)
    assert model.n_points == 300 and np.isfinite(model.positions).all()


def test_spz_extension_records_beyond_the_bound_are_dropped_with_a_warning(tmp_path):
    from splatdeform.io.splats import SplatFields

    n = 50
    rng = np.random.default_rng(7)
    f = SplatFields(positions=rng.normal(size=(n, 3)), scale_log=np.full((n, 3), -3, np.float32),
                    rotation=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                    opacity=np.zeros(n, np.float32), sh_dc=np.zeros((n, 3), np.float32),
                    sh_rest=np.zeros((n, 3, 0), np.float32))
    records = [(0x10000 + i, b"") for i in range(200_000)]
    path = tmp_path / "records.spz"
    path.write_bytes(spz.write_v4(spz.encode(f, version=4), records))
    with pytest.warns(UserWarning, match="200,000 SPZ extension records"):
        model = load(path)
    assert not any(c.startswith(spz.EXTENSION_COMMENT) for c in model.source.comments)
    res = run_cli("convert", path, tmp_path / "out.ply")
    assert res.returncode == 0, res.stderr
    assert len([ln for ln in res.stderr.splitlines() if "extension records" in ln]) == 1
    assert load(tmp_path / "out.ply").n_points == n   # what we wrote, we read back
    # a few records are still kept and written back
    few = tmp_path / "few.spz"
    few.write_bytes(spz.write_v4(spz.encode(f, version=4), records[:3]))
    assert spz.extensions_of(load(few)) == records[:3]


def test_out_of_memory_names_the_file_and_what_it_declared(tmp_path):
    """A load that still runs out of memory (here under an address-space cap 40 MB above the
    child's own) says so in one line naming the file and the count its header declares."""
    import subprocess
    import sys

    n = 3_000_000
    src = _pcd_binary(tmp_path / "cloud.pcd", n)
    code = ("import re, resource, sys\n"
            "from splatdeform.io import load\n"
            "from splatdeform.errors import SplatdeformError\n"
            "vm = int(re.search(r'VmSize:\\s+(\\d+)', open('/proc/self/status').read())[1])\n"
            "resource.setrlimit(resource.RLIMIT_AS, ((vm << 10) + (40 << 20),) * 2)\n"
            "try:\n    load(sys.argv[1])\nexcept SplatdeformError as exc:\n"
            "    print(exc)\n    sys.exit(exc.exit_code)\n")
    res = subprocess.run([sys.executable, "-c", code, str(src)], capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 1, (res.stdout, res.stderr[-2000:])
    assert "cloud.pcd: out of memory" in res.stdout
    assert f"declaring {n:,} points" in res.stdout


def _pcd_binary(path: Path, n: int) -> Path:
    head = (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\n"
            f"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n").encode()
    path.write_bytes(head + np.zeros(3 * n, "<f4").tobytes())
    return path
