"""``splatdeform batch`` against hostile inputs and faults (issue 11): FIFOs and devices named
``*.ply``, archive members that lie about their size, duplicate member names, stale temporary
folders, and scans that run too long. Real worker processes, real archives, real signals;
subprocess timeouts turn a hang into a failure.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
import warnings
import zipfile
from pathlib import Path

import helpers
import pytest
import yaml
from helpers import batch_edit, dead_pid, write_batch
from helpers import batch_report as report

from data_tools.make_archive import make_scans
from splatdeform.batch.extract import _host, clean_stale_temps, materialize
from splatdeform.batch.probe import HEAD_BYTES, check, estimate_memory, probe
from splatdeform.batch.sources import Scan
from splatdeform.cli import main
from splatdeform.errors import InputError
from splatdeform.io import load

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
EDIT = batch_edit()
BIN_HEADER = (b"ply\nformat binary_little_endian 1.0\ncomment element vertex 999999999\n"
              b"element vertex 10\nproperty float x\nproperty float y\nproperty float z\n"
              b"end_header\n")
ASCII_HEADER = BIN_HEADER.replace(b"binary_little_endian", b"ascii")


@pytest.fixture(scope="module")
def bars(tmp_path_factory) -> list[Path]:
    """Two small generated bar scans (good input)."""
    paths, _ = make_scans(tmp_path_factory.mktemp("bars"), 2, 1500, spheres=False,
                          zip_name=None)
    return paths


def run_cli(*args, env: dict | None = None, fsize: int | None = None,
            timeout: float = 180) -> subprocess.CompletedProcess:
    def limit() -> None:
        if fsize is not None:   # a write past this kills the process (SIGXFSZ)
            resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

    return helpers.run_cli(*args, env=env, timeout=timeout, preexec_fn=limit)


def temps(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("splatdeform-batch-"))


# -- non-regular files ---------------------------------------------------------------------------

def test_fifo_and_device_named_ply_fail_without_hanging(tmp_path: Path, bars) -> None:
    scans = tmp_path / "scans"
    scans.mkdir()
    for p in bars:
        (scans / p.name).write_bytes(p.read_bytes())
    os.mkfifo(scans / "pipe.ply")
    os.mkfifo(scans / "pipe.zip")
    (scans / "zero.ply").symlink_to("/dev/zero")
    cfg = write_batch(tmp_path / "b.yaml", scans="scans", output_dir="out")
    r = run_cli("batch", cfg, "--workers", "2", "--quiet", timeout=120)
    assert r.returncode == 1, r.stderr
    rows = report(tmp_path / "out")
    assert len(rows) == 5
    for name in ("pipe.ply", "pipe.zip"):
        row = rows[str(scans / name)]
        assert row["status"] == "failed" and "FIFO" in row["error"]
    assert "character device" in rows[str(scans / "zero.ply")]["error"]
    assert all(rows[str(scans / p.name)]["status"] == "ok" for p in bars)
    assert len(list((tmp_path / "out").glob("*_deformed.ply"))) == 2
    err = r.stderr.strip().splitlines()
    assert sum("pipe.ply" in line for line in err) == 1   # one line per failed scan
    assert "Traceback" not in r.stderr


def test_materialize_refuses_a_fifo_without_blocking(tmp_path: Path) -> None:
    fifo = tmp_path / "late.ply"
    os.mkfifo(fifo)   # e.g. swapped in after the scans were listed
    result: list[BaseException | None] = []

    def attempt() -> None:
        try:
            with materialize(Scan(str(fifo)), lambda head, size: None):
                result.append(None)
        except BaseException as exc:  # noqa: BLE001 - recorded and checked below
            result.append(exc)

    t = threading.Thread(target=attempt, daemon=True)
    t.start()
    t.join(20)
    assert not t.is_alive(), "materialize blocked on a FIFO"
    assert isinstance(result[0], InputError) and "FIFO" in str(result[0])


@pytest.mark.parametrize("case", ["fifo_output", "edit_is_report", "output_dir_is_file",
                                  "device_thumbnail"])
def test_outputs_never_replace_inputs_or_special_files(tmp_path: Path, bars, case,
                                                       capsys) -> None:
    """Checked before any work: exit 2, one line naming the path, nothing written."""
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / bars[0].name).write_bytes(bars[0].read_bytes())
    out = tmp_path / "out"
    keys = {"scans": "scans", "output_dir": "out"}
    if case == "fifo_output":
        out.mkdir()
        os.mkfifo(out / f"{bars[0].stem}_deformed.ply")
        expected = "exists and is a FIFO"
    elif case == "edit_is_report":   # a JSON edit file kept in the output folder
        out.mkdir()
        (out / "report.json").write_text(json.dumps(EDIT))
        keys["edit"] = "out/report.json"
        expected = "is the edit file"
    elif case == "output_dir_is_file":
        out.write_text("a file")
        expected = "output_dir"
    else:
        out.mkdir()
        (out / f"{bars[0].stem}.png").symlink_to("/dev/null")
        keys["render"] = {"size": [64, 64]}
        expected = "character device"
    cfg = tmp_path / "b.yaml"
    cfg.write_text(yaml.safe_dump({"edit": EDIT, **keys}))
    before = sorted(p.name for p in out.iterdir()) if out.is_dir() else None
    assert main(["batch", str(cfg), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err and "b.yaml" in err, err
    if before is not None:
        assert sorted(p.name for p in out.iterdir()) == before


# -- archive members that lie about their size ---------------------------------------------------

def test_probe_reads_the_header_with_the_ply_parser() -> None:
    p = probe("a.ply", BIN_HEADER, len(BIN_HEADER) + 120)
    assert p.points == 10 and not p.text   # not the count in the comment
    assert p.max_size == len(BIN_HEADER) + 120 + (1 << 20)
    check("a.ply", p)   # a well-formed file passes
    big = probe("a.ply", BIN_HEADER, 2 << 30)
    with pytest.raises(InputError, match="a.ply: the file is 2,147,483,648 bytes"):
        check("a.ply", big)
    text = probe("a.ply", ASCII_HEADER, 2 << 30)
    assert text.max_size is None and text.points == 10
    assert estimate_memory(text) > 2 << 30   # the size counts, not only the header's points
    check("a.ply", text)   # the budget is the one budget rule's (memory.choose), not the probe's
    assert probe("a.xyz", b"1 2 3\n", 1200).points == 100
    assert len(BIN_HEADER) < HEAD_BYTES


def test_probe_counts_las_points_from_the_header() -> None:
    from conftest import shared_file

    for name in ("lidar/simple.laz", "lidar/vegetation_1_3.las"):
        path = shared_file(name)
        raw = path.read_bytes()
        assert probe(path.name, raw[:HEAD_BYTES], len(raw)).points == load(path).n_points


def test_lying_archive_members_fail_before_extraction(tmp_path: Path, bars) -> None:
    """A PLY header plus 256 MiB of zeros: binary (the header bounds the size) and ascii (the
    memory budget does). Extraction would hit RLIMIT_FSIZE and kill the worker instead."""
    archive = tmp_path / "lies.zip"
    zeros = bytes(1 << 24)
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        zf.write(bars[0], "good.ply")
        for name, header in (("bomb.ply", BIN_HEADER), ("bomb_ascii.ply", ASCII_HEADER)):
            with zf.open(name, "w") as f:
                f.write(header)
                for _ in range(16):
                    f.write(zeros)
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    dead = dead_pid()
    stale = tmp / f"splatdeform-batch-{dead}-{_host()}-killed1"   # a killed run's leftovers
    (stale / "scans").mkdir(parents=True)
    (stale / "scans" / "half.ply").write_bytes(b"ply\n")
    kept = [tmp / f"splatdeform-batch-{os.getpid()}-{_host()}-alive1",   # a live process
            tmp / f"splatdeform-batch-{dead}-otherhost-remote1",          # another machine
            tmp / "splatdeform-batch-legacy12"]                          # not ours to judge
    for k in kept:
        k.mkdir()
    cfg = write_batch(tmp_path / "b.yaml", scans="lies.zip", output_dir="out",
                      memory_per_worker_mb=1000)
    r = run_cli("batch", cfg, "--workers", "1", "--quiet", env={"TMPDIR": str(tmp)},
                fsize=64 << 20)
    assert r.returncode == 1, r.stderr
    rows = report(tmp_path / "out")
    assert rows["lies.zip:good.ply"]["status"] == "ok"
    assert "header declares at most" in rows["lies.zip:bomb.ply"]["error"]
    assert "MiB per worker" in rows["lies.zip:bomb_ascii.ply"]["error"]
    assert not any("died" in row["error"] for row in rows.values())
    assert temps(tmp) == sorted(k.name for k in kept)


def test_duplicate_member_names_are_not_merged(tmp_path: Path, bars) -> None:
    good, other = bars[0].read_bytes(), bars[1].read_bytes()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)   # zipfile: "Duplicate name"
        with zipfile.ZipFile(tmp_path / "d.zip", "w") as zf:
            zf.writestr("scans/a.ply", good)
            zf.writestr("scans/a.ply", b"ply\nnot a scan\n")
    with tarfile.open(tmp_path / "d.tar", "w") as tf:
        for data in (other, b"garbage"):
            src = tmp_path / "member"
            src.write_bytes(data)
            tf.add(src, "b.ply")
    cfg = write_batch(tmp_path / "b.yaml", scans=["d.zip", "d.tar"], output_dir="out")
    from splatdeform.batch import run_batch

    summary = run_batch(cfg, workers=1, quiet=True)
    assert summary["counts"] == {"ok": 2, "failed": 2, "skipped": 0}
    rows = report(tmp_path / "out")
    assert set(rows) == {"d.zip:scans/a.ply", "d.zip:scans/a.ply#2", "d.tar:b.ply",
                         "d.tar:b.ply#2"}
    for first in ("d.zip:scans/a.ply", "d.tar:b.ply"):
        assert rows[first]["status"] == "ok"
        assert rows[first + "#2"]["status"] == "failed"
        assert "duplicate member name" in rows[first + "#2"]["error"]
    # each output comes from the first (valid) entry
    assert load(tmp_path / "out" / "a_deformed.ply").n_points == load(bars[0]).n_points
    assert load(tmp_path / "out" / "b_deformed.ply").n_points == load(bars[1]).n_points


def test_clean_stale_temps_only_removes_dead_own_folders(tmp_path: Path) -> None:
    dead = dead_pid()
    mine_dead = tmp_path / f"splatdeform-batch-{dead}-{_host()}-x1"
    mine_live = tmp_path / f"splatdeform-batch-{os.getpid()}-{_host()}-x2"
    a_file = tmp_path / f"splatdeform-batch-{dead}-{_host()}-x3"
    other = tmp_path / f"other-{dead}-{_host()}-x4"
    for d in (mine_dead, mine_live, other):
        d.mkdir()
    a_file.write_text("not a folder")
    assert clean_stale_temps(str(tmp_path)) == [str(mine_dead)]
    assert mine_live.is_dir() and other.is_dir() and a_file.is_file()
    # temporary outputs in output_dir: only the atomic writer's exact names of dead writers go;
    # a live writer's (another batch's) and every look-alike stay
    from splatdeform.io.atomic import remove_stale_temps

    out = tmp_path / "out"
    out.mkdir()
    names = [f".bar.{dead}-abc123xy.tmp.ply", f".bar.{os.getpid()}-abc123xy.tmp.ply",
             ".bar.abc12345.tmp.ply", f".bar.{dead}-abc123.tmp.ply", ".keep.yaml", "bar.ply"]
    for n in names:
        (out / n).write_text("x")
    assert remove_stale_temps(out, any_output=True) == [out / names[0]]
    assert sorted(p.name for p in out.iterdir()) == sorted(names[1:])


# -- per-scan timeout ----------------------------------------------------------------------------

def hang_in_slow_scans(job):
    """Task for run_local: scans named 'slow' hang while their member is extracted."""
    from splatdeform.batch.extract import materialize
    from splatdeform.batch.worker import process_scan

    if "slow" in job.scan.name:
        with materialize(job.scan):
            time.sleep(600)
    return process_scan(job)


def test_scan_timeout_stops_only_the_slow_scan(tmp_path: Path, bars, monkeypatch) -> None:
    from splatdeform.batch import load_batch
    from splatdeform.batch.runner import run_local

    with zipfile.ZipFile(tmp_path / "s.zip", "w") as zf:
        zf.write(bars[0], "slow.ply")
        for p in bars:
            zf.write(p, p.name)
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))           # the workers' temp folder
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))   # and this process's
    jobs = load_batch(write_batch(tmp_path / "b.yaml", scans="s.zip", output_dir="out")).jobs
    got = {r["scan"]: r for r in run_local(jobs, 2, lambda r: None, fn=hang_in_slow_scans,
                                           timeout=6.0)}
    assert got["s.zip:slow.ply"]["status"] == "failed"
    assert "timed out" in got["s.zip:slow.ply"]["error"]
    assert all(got[f"s.zip:{p.name}"]["status"] == "ok" for p in bars)
    assert temps(tmp) == []   # the stopped scan's extraction folder is gone


def test_scan_timeout_config_and_cli(tmp_path: Path, bars, capsys) -> None:
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / bars[0].name).write_bytes(bars[0].read_bytes())
    cfg = write_batch(tmp_path / "b.yaml", scans="scans", output_dir="out",
                      scan_timeout_s=0.001)   # no scan deforms in a millisecond
    assert main(["batch", str(cfg), "--workers", "1", "--quiet"]) == 1
    (row,) = report(tmp_path / "out").values()
    assert row["status"] == "failed" and "timed out" in row["error"]
    assert "timed out" in capsys.readouterr().err
    assert main(["batch", str(cfg), "--workers", "1", "--quiet", "--scan-timeout", "600"]) == 0
    (row,) = report(tmp_path / "out").values()
    assert row["status"] == "ok"                     # the command line wins
    summary = json.loads((tmp_path / "out" / "report.json").read_text())
    assert summary["scan_timeout_s"] == 600


@pytest.mark.parametrize("args, key", [
    (["--scan-timeout", "-1"], "--scan-timeout"),
    (["--scan-timeout", "nan"], "--scan-timeout"),
    (["--scan-timeout", "inf"], "--scan-timeout"),
    (["--scan-timeout", "soon"], "--scan-timeout"),
    ({"scan_timeout_s": 0}, "scan_timeout_s"),
    ({"scan_timeout_s": float("nan")}, "scan_timeout_s"),
    ({"scan_timeout_s": "ten"}, "scan_timeout_s"),
])
def test_bad_timeouts_exit_2_one_line(tmp_path: Path, bars, args, key, capsys) -> None:
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / bars[0].name).write_bytes(bars[0].read_bytes())
    extra = args if isinstance(args, dict) else {}
    cfg = write_batch(tmp_path / "b.yaml", scans="scans", output_dir="out", **extra)
    argv = ["batch", str(cfg)] + (args if isinstance(args, list) else [])
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and key in err
    if isinstance(args, list):  # says what a timeout must be (not "invalid <lambda> value")
        assert "<lambda>" not in err and "expected a number of seconds" in err
    assert not (tmp_path / "out").exists()


def test_dask_scan_timeout(tmp_path: Path, bars) -> None:
    """On Dask each scan runs in a child process of the worker when a time limit is set."""
    import distributed

    from splatdeform.batch import run_batch

    (tmp_path / "scans").mkdir()
    bar = bars[0]
    (tmp_path / "scans" / bar.name).write_bytes(bar.read_bytes())
    cfg = write_batch(tmp_path / "b.yaml", scans="scans", output_dir="out")
    with distributed.LocalCluster(n_workers=1, processes=True, threads_per_worker=1,
                                  dashboard_address=None) as cluster:
        tiny = run_batch(cfg, scheduler=cluster.scheduler_address, quiet=True,
                         scan_timeout=0.001)
        ample = run_batch(cfg, scheduler=cluster.scheduler_address, quiet=True,
                          scan_timeout=600, force=True)
    assert tiny["counts"]["failed"] == 1 and "timed out" in tiny["rows"][0]["error"]
    assert ample["counts"] == {"ok": 1, "failed": 0, "skipped": 0}
    assert load(tmp_path / "out" / f"{bar.stem}_deformed.ply").n_points == load(bar).n_points
