"""Budget refusals: the memory estimate reads the validated header (never a second
parser), and an explicit ``--memory-budget`` is a cap (issue 32, items 2 and 9).

- a LAS/LAZ whose header declares 2^31 VLRs is refused by ``render`` at once (one line, exit 2),
  as ``info`` refuses it: the estimate goes through ``io/las_header.py``'s checks;
- a PCD's point count is the header's POINTS (WIDTH x HEIGHT) for every DATA encoding,
  ``binary_compressed`` included (not a guess from the file size);
- ``deform --memory-budget B`` on PLY, LAS, LAZ (one LAZ written as a single compressed chunk)
  and PCD below their in-memory need: the streamable formats stream with a peak RSS (the child's
  VmHWM) of at most B + :data:`splatdeform.memory.BUDGET_MARGIN`; PCD, which does not stream,
  is refused with one line naming the estimate and the budget;
- the default budget (half the RAM) keeps the rule from before the cap.
"""

from __future__ import annotations

import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import ROOT, bar_edit, shared_file
from helpers import cpu_time, run_cli_peak

from data_tools.synth import bumpy_bar
from splatdeform import memory
from splatdeform.errors import FormatError, InputError

MB = 2**20
EDIT = bar_edit({"translate": [0, 0.1, 0]}, backend="numpy")

def run_cli(*args: str, timeout: float = 120) -> tuple[subprocess.CompletedProcess, int]:
    """(the finished process, its peak RSS in bytes) of ``splatdeform ARGS``."""
    return run_cli_peak(*args, cwd=ROOT, timeout=timeout)


def errors(r: subprocess.CompletedProcess) -> list[str]:
    return [ln for ln in r.stderr.splitlines() if ln.strip()]


def write_edit(folder: Path, inp: Path, out: str) -> Path:
    path = folder / f"edit_{out.replace('.', '_')}.yaml"
    path.write_text(yaml.safe_dump(dict(EDIT, input=str(inp), output=out)))
    return path


# -- item 2: the estimate reads the validated header ---------------------------------------------

def corrupt_vlr_count(src: Path, out: Path) -> Path:
    raw = bytearray(src.read_bytes())
    struct.pack_into("<I", raw, 100, 2**31)   # number of VLRs (LAS header offset 100)
    out.write_bytes(bytes(raw))
    return out


@pytest.mark.parametrize("name", ["lidar/vegetation_1_3.las", "lidar/simple.laz"])
def test_corrupt_vlr_count_is_refused_by_the_estimate(tmp_path: Path, name: str) -> None:
    bad = corrupt_vlr_count(shared_file(name), tmp_path / Path(name).name)
    with cpu_time() as cpu, pytest.raises(FormatError, match="2147483648 VLRs declared"):
        memory.file_cost(bad)
    assert cpu.seconds < 2.0   # CPU seconds: the 2^31 records are never walked
    # the batch guard's estimate from the first bytes runs the same checks
    with pytest.raises(FormatError, match="VLRs declared"):
        memory.head_cost(bad.name, bad.read_bytes()[:memory.HEAD_BYTES], bad.stat().st_size)


def test_render_of_a_corrupt_vlr_count_fails_fast_with_one_line(tmp_path: Path) -> None:
    bad = corrupt_vlr_count(shared_file("lidar/vegetation_1_3.las"), tmp_path / "vlr.las")
    with cpu_time() as cpu:
        r, _ = run_cli("render", str(bad), "-o", str(tmp_path / "x.png"), timeout=120)
    assert r.returncode == 2, r.stderr
    err = errors(r)
    assert len(err) == 1 and "Traceback" not in r.stderr, r.stderr
    assert err[0].startswith(f"splatdeform: error: {bad}: corrupt LAS/LAZ header") and \
        "VLRs" in err[0]
    assert cpu.seconds < 10   # the child's CPU, interpreter start and imports included
    assert not (tmp_path / "x.png").exists()


@pytest.fixture(scope="module")
def terrain_pcd(tmp_path_factory) -> Path:
    """The real 522,674-point LiDAR terrain as a binary_compressed PCD."""
    from dataclasses import replace

    from splatdeform.io import load, pcd, save

    folder = tmp_path_factory.mktemp("pcd")
    save(load(shared_file("scans/lidar_terrain_522k.ply")), folder / "plain.pcd")
    source, _ = pcd.read_source(folder / "plain.pcd")
    out = folder / "terrain_compressed.pcd"
    with open(out, "wb") as f:
        pcd.write_source(replace(source, encoding="binary_compressed"), f)
    return out


def test_pcd_binary_compressed_count_is_the_headers(terrain_pcd: Path) -> None:
    from splatdeform.io import pcd

    source, _, size = pcd.read_header(terrain_pcd)
    assert source.encoding == "binary_compressed" and source.width * source.height == 522_674
    cost = memory.file_cost(terrain_pcd)
    assert cost.points == 522_674 and cost.size == size
    # PCL's own LZF-compressed organized frame: the header's 640 x 480
    real = shared_file("pcd/osd_learn0_organized.pcd")
    assert memory.file_cost(real).points == 307_200
    head = real.read_bytes()[:memory.HEAD_BYTES]
    assert memory.head_cost(real.name, head, real.stat().st_size).points == 307_200


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_pcd_count_for_every_encoding_and_lies_refused(tmp_path: Path, encoding: str) -> None:
    from dataclasses import replace

    from splatdeform.io import pcd, save

    save(bumpy_bar(3_000, seed=2), tmp_path / "a.pcd")
    source, _ = pcd.read_source(tmp_path / "a.pcd")
    path = tmp_path / f"{encoding}.pcd"
    with open(path, "wb") as f:
        pcd.write_source(replace(source, encoding=encoding), f)
    assert memory.file_cost(path).points == 3_000
    # a header declaring more points than the body holds is refused by the estimate
    raw = path.read_bytes().replace(b"WIDTH 3000", b"WIDTH 3000000", 1) \
        .replace(b"POINTS 3000", b"POINTS 3000000", 1)
    lie = tmp_path / f"lie_{encoding}.pcd"
    lie.write_bytes(raw)
    with pytest.raises(FormatError, match=f"{lie.name}: PCD"):
        memory.file_cost(lie)


def test_estimate_opens_with_the_one_opener(tmp_path: Path) -> None:
    import os

    fifo = tmp_path / "pipe.las"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="named pipe"):
        memory.file_cost(fifo)   # refused, not blocked on


# -- item 9: an explicit budget is a cap ----------------------------------------------------------

@pytest.fixture(scope="module")
def bars(tmp_path_factory) -> dict[str, Path]:
    """A 300k-point surfel bar as binary PLY, LAS and LAZ, and as a LAZ written as one single
    compressed chunk (lazrs's parallel decompressor would hold it all decompressed)."""
    import lazrs

    from splatdeform.io import save

    folder = tmp_path_factory.mktemp("bars")
    model = bumpy_bar(300_000, seed=7)
    out = {ext: folder / f"bar.{ext}" for ext in ("ply", "las", "laz")}
    for path in out.values():
        save(model, path)
    original = lazrs.LazVlr.new_for_compression

    def one_chunk(point_format, extra_bytes, use_variable_size_chunks=False):
        data = bytearray(original(point_format, extra_bytes).record_data())
        struct.pack_into("<I", data, 12, 300_000)   # chunk size (LASzip VLR offset 12)
        return lazrs.LazVlr(bytes(data))

    lazrs.LazVlr.new_for_compression = staticmethod(one_chunk)
    try:
        out["one_chunk.laz"] = folder / "one_chunk.laz"
        save(model, out["one_chunk.laz"])
    finally:
        lazrs.LazVlr.new_for_compression = original
    return out


BUDGET = "160MB"


@pytest.mark.parametrize("kind", ["ply", "las", "laz", "one_chunk.laz"])
def test_budget_below_the_need_streams_within_budget_plus_margin(bars, tmp_path: Path,
                                                                 kind: str) -> None:
    inp = bars[kind]
    budget = memory.parse_size(BUDGET)
    cost = memory.file_cost(inp)
    assert memory.deform_peak(cost) > budget   # the in-memory run would not fit
    if kind == "one_chunk.laz":
        from splatdeform.io.las_header import check_header

        assert check_header(inp).laz_chunk_points == 300_000
        assert cost.reader_bytes > 5 * MB   # the compressed chunk the reader holds is counted
    ext = inp.suffix
    cfg = write_edit(tmp_path, inp, f"out{ext}")
    r, peak = run_cli("deform", str(cfg), "--memory-budget", BUDGET, timeout=180)
    assert r.returncode == 0, r.stderr
    assert "streaming 300,000 points" in r.stdout
    assert peak <= budget + memory.BUDGET_MARGIN, (kind, peak / MB)
    assert (tmp_path / f"out{ext}").is_file()


def test_pcd_over_an_explicit_budget_is_refused_with_one_line(terrain_pcd: Path,
                                                              tmp_path: Path) -> None:
    cfg = write_edit(tmp_path, terrain_pcd, "out.pcd")
    r, peak = run_cli("deform", str(cfg), "--memory-budget", "64MB", timeout=60)
    assert r.returncode == 2, r.stderr
    err = errors(r)
    assert len(err) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "in-memory estimate is" in err[0] and "memory budget of 64 MB" in err[0]
    assert ".pcd files do not stream" in err[0]
    assert peak <= memory.parse_size("64MB") + memory.BUDGET_MARGIN
    assert not (tmp_path / "out.pcd").exists()
    # the config key is the same cap
    data = yaml.safe_load(cfg.read_text())
    cfg.write_text(yaml.safe_dump(dict(data, memory_budget="64MB")))
    r, _ = run_cli("deform", str(cfg), timeout=60)
    assert r.returncode == 2 and "memory budget of 64 MB" in errors(r)[0]


def test_the_one_rule() -> None:
    big = 10 * 2**40   # more than any default budget
    assert memory.choose(10 * MB, 64 * MB, streamable=False).mode == "memory"
    assert memory.choose(100 * MB, 64 * MB, streamable=True).mode == "stream"
    refused = memory.choose(100 * MB, 64 * MB, streamable=False, name="a.pcd",
                            why_not=".pcd files do not stream")
    assert refused.mode == "refuse" and "100 MB" in refused.message and \
        "64 MB" in refused.message and refused.message.startswith("a.pcd: ")
    whole = memory.choose(100 * MB, 64 * MB, streamable=True, whole="--reuse")
    assert whole.mode == "refuse" and "--reuse needs the whole model" in whole.message
    # the default budget (half the RAM): today's rule, a warning and in memory
    default = memory.choose(big, None, streamable=True, name="x.ply", whole="--reuse")
    assert default.mode == "memory" and "running in memory" in default.message
    assert memory.choose(big, None, streamable=True).mode == "stream"
    assert memory.choose(big, None, streamable=False).mode == "memory"


def test_config_budget_with_reuse_is_refused_not_ignored(bars, tmp_path: Path) -> None:
    from splatdeform.edit.config import load_edit
    from splatdeform.edit.run import streams
    from splatdeform.edit.stream import StreamOptions

    cfg = load_edit(write_edit(tmp_path, bars["ply"], "o.ply"))
    options = StreamOptions()
    with pytest.raises(InputError, match="--reuse needs the whole model"):
        streams(cfg, bars["ply"], options, memory.parse_size("64MB"), reuse=tmp_path / "r.npz")
    warned: list[str] = []
    assert not streams(cfg, bars["ply"], options, None, reuse=tmp_path / "r.npz",
                       warn=warned.append) or not warned   # default budget: today's rule
    assert streams(cfg, bars["ply"], options, memory.parse_size("64MB"))


def test_stream_chunk_leaves_room_for_the_laz_reader() -> None:
    plain = memory.stream_chunk(160 * MB, 48, memory.BASE_BYTES)
    with_reader = memory.stream_chunk(160 * MB, 48, memory.BASE_BYTES + 30 * MB)
    assert with_reader <= plain
    assert memory.laz_reader_bytes(10 * MB, 50_000, 48) == 50_000 * 48
    assert memory.laz_reader_bytes(10 * MB, 0, 48) == 10 * MB   # variable chunks: all of it
    assert memory.laz_reader_bytes(10 * MB, 50_000, 48, parallel=True) > 50_000 * 48 * 2
    assert np.isfinite(memory.LAZ_PARALLEL_COPIES)
