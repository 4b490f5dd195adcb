"""``splatdeform batch``: folders and archives, failure isolation, resume, Dask, kill safety."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import helpers
import numpy as np
import pytest
import yaml
from conftest import bar_edit

from data_tools.make_archive import make_scans
from splatdeform.batch.config import deep_merge
from splatdeform.cli import main
from splatdeform.io import load

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable

EDIT = bar_edit({"pivot": [0.75, 0.5, 0.5], "rotate": {"axis": [0, 0, 1], "degrees": 30},
                 "translate": [0, 0.1, 0]}, fit={"tolerance": 1e-3, "max_centers": 400})
GOOD = ["bar_000", "bar_001", "bar_002", "sphere_003", "bar_004", "bar_005"]
BROKEN = ["bar_006_truncated", "sphere_007_nan"]


@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("batch")
    make_scans(root, 8, 3000, broken=True)
    return root


def write_batch(path: Path, **keys) -> Path:
    data = {"edit": EDIT, **keys}
    path.write_text(yaml.safe_dump(data))
    return path


def outputs(out: Path) -> dict[str, Path]:
    return {p.name[: -len("_deformed.ply")]: p for p in out.glob("*_deformed.ply")}


def rows(out: Path) -> dict[str, dict]:
    data = json.loads((out / "report.json").read_text())
    return {Path(r["scan"].split(":")[-1]).stem: r for r in data["scans"]}


def run_cli(*args: str | Path) -> subprocess.CompletedProcess:
    return helpers.run_cli(*args, timeout=300)


@pytest.fixture(scope="module")
def local_run(scans: Path) -> Path:
    """The folder batch on 2 local workers, with thumbnails; returns its output_dir."""
    cfg = write_batch(scans / "folder.yaml", scans="scans", output_dir="out_folder",
                      render={"size": [128, 128]})
    assert main(["batch", str(cfg), "--workers", "2", "--quiet"]) == 1
    return scans / "out_folder"


def test_folder_batch_isolates_failures_and_reports(local_run: Path) -> None:
    assert sorted(outputs(local_run)) == sorted(GOOD)
    for p in outputs(local_run).values():
        assert load(p).n_points > 2000
    r = rows(local_run)
    assert {k for k, v in r.items() if v["status"] == "ok"} == set(GOOD)
    assert "truncated" in r["bar_006_truncated"]["error"]
    assert "NaN" in r["sphere_007_nan"]["error"]
    assert all(r[k]["status"] == "failed" for k in BROKEN)
    assert all(r[k]["centers"] > 0 and r[k]["constraint_error_rel"] < 1e-2 for k in GOOD)
    csv = (local_run / "report.csv").read_text().splitlines()
    assert len(csv) == 9 and csv[0].startswith("scan,status,points")
    html = (local_run / "index.html").read_text()
    for name in GOOD:
        assert f'src="./{name}.png"' in html and (local_run / f"{name}.png").stat().st_size > 0
    assert html.count('class="card failed"') == 2


def test_rerun_skips_and_force_redoes(scans: Path, local_run: Path, capsys) -> None:
    cfg = scans / "folder.yaml"
    before = {k: p.stat().st_mtime_ns for k, p in outputs(local_run).items()}
    assert main(["batch", str(cfg), "--workers", "2", "--quiet"]) == 1
    r = rows(local_run)
    assert {k for k, v in r.items() if v["status"] == "skipped"} == set(GOOD)
    assert {k: p.stat().st_mtime_ns for k, p in outputs(local_run).items()} == before
    assert main(["batch", str(cfg), "--workers", "2", "--force", "--quiet"]) == 1
    r = rows(local_run)
    assert {k for k, v in r.items() if v["status"] == "ok"} == set(GOOD)
    assert all(p.stat().st_mtime_ns != before[k] for k, p in outputs(local_run).items())
    err = capsys.readouterr().err
    assert "bar_006_truncated" in err and "6 ok, 2 failed" in err


def test_zip_archive_matches_folder(scans: Path, local_run: Path) -> None:
    cfg = write_batch(scans / "zip.yaml", scans="scans.zip", output_dir="out_zip", workers=2)
    assert main(["batch", str(cfg), "--quiet"]) == 1
    out = outputs(scans / "out_zip")
    assert sorted(out) == sorted(GOOD)
    r = rows(scans / "out_zip")
    assert r["bar_006_truncated"]["status"] == "failed"
    assert "scans.zip:scans/bar_006_truncated.ply" in r["bar_006_truncated"]["error"]
    ref = outputs(local_run)
    for name, p in out.items():
        assert np.array_equal(load(p).positions, load(ref[name]).positions)


def test_dask_local_cluster_matches_local(scans: Path, local_run: Path) -> None:
    import distributed

    from splatdeform.batch import run_batch

    cfg = write_batch(scans / "dask.yaml", scans="scans/*.ply", output_dir="out_dask")
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1,
                                  dashboard_address=None) as cluster:
        summary = run_batch(cfg, scheduler=cluster.scheduler_address, quiet=True)
    assert summary["exit_code"] == 1
    assert summary["counts"] == {"ok": 6, "failed": 2, "skipped": 0}
    out, ref = outputs(scans / "out_dask"), outputs(local_run)
    assert sorted(out) == sorted(ref)
    for name, p in out.items():
        a, b = load(p), load(ref[name])
        assert np.array_equal(a.positions, b.positions)
        assert np.array_equal(a.normals, b.normals)


def test_kill_mid_run_then_resume(scans: Path) -> None:
    cfg = write_batch(scans / "kill.yaml", scans="scans", output_dir="out_kill")
    out = scans / "out_kill"
    proc = subprocess.Popen([PY, "-m", "splatdeform.cli", "batch", str(cfg), "--workers", "1",
                             "--quiet"], cwd=ROOT, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None and not outputs(out):
        time.sleep(0.02)
    assert proc.poll() is None, "the batch finished before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()

    def group_gone() -> bool:   # the killed batch's worker processes too
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            return True
        return False

    helpers.wait_for(group_gone, 30, "the killed batch's process group to end")
    done = outputs(out)
    assert 1 <= len(done) < 6
    for p in done:   # every output present is complete
        assert load(done[p]).n_points > 2000
    assert not (out / "report.json").exists()
    finished = {k for k in done if (out / f"{k}_deformed.ply.json").exists()}   # before rerun
    r = run_cli("batch", cfg, "--workers", "2", "--quiet")
    assert r.returncode == 1, r.stderr
    assert sorted(outputs(out)) == sorted(GOOD)
    statuses = {k: v["status"] for k, v in rows(out).items()}
    assert {k for k, v in statuses.items() if v == "skipped"} == finished
    assert not [p for p in out.iterdir() if ".tmp" in p.name]
    for p in outputs(out).values():
        assert load(p).n_points > 2000


def test_memory_budget_fails_scans_with_a_message(scans: Path) -> None:
    from splatdeform.batch import run_batch

    cfg = write_batch(scans / "mem.yaml", scans="scans/bar_00[0-1].ply", output_dir="out_mem",
                      memory_per_worker_mb=1)
    summary = run_batch(cfg, workers=1, quiet=True)
    assert summary["exit_code"] == 1
    assert all("MiB" in r["error"] and r["status"] == "failed" for r in summary["rows"])
    assert not outputs(scans / "out_mem")


@pytest.mark.parametrize("keys, expected", [
    ({"scans": "scans", "output_dir": "o", "wokers": 2}, "wokers: unknown key"),
    ({"scans": "nothing/*.ply", "output_dir": "o"}, "scans: no scans matched"),
    ({"scans": "scans", "output_dir": "scans/out"}, "output_dir:"),
    ({"scans": "scans/**/*.ply", "output_dir": "scans/out"}, "output_dir:"),
    ({"scans": "scans", "output_dir": "o", "edit": {"regions": {"fixed": []}}},
     "edit.regions.fixed"),
])
def test_bad_batch_configs_exit_2_one_line(scans: Path, tmp_path: Path, keys, expected,
                                           capsys) -> None:
    (tmp_path / "scans").symlink_to(scans / "scans")
    data = {"edit": EDIT, **keys}
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(yaml.safe_dump(data))
    assert main(["batch", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err and "bad.yaml" in err


def test_deep_merge_and_overrides(scans: Path) -> None:
    from splatdeform.batch import load_batch

    assert deep_merge({"a": {"b": 1, "c": 2}, "d": [1]}, {"a": {"b": 5}, "d": [2]}) == \
        {"a": {"b": 5, "c": 2}, "d": [2]}
    cfg = write_batch(scans / "ov.yaml", scans="scans/*.ply", output_dir="out_ov",
                      overrides=[{"match": "sphere_*",
                                  "edit": {"handle": {"transform": {"rotate": {"degrees": 5}}}}}])
    batch = load_batch(cfg)
    deg = {Path(j.output).name: j.edit["handle"]["transform"]["rotate"]["degrees"]
           for j in batch.jobs}
    assert deg["sphere_003_deformed.ply"] == 5 and deg["bar_000_deformed.ply"] == 30
    hashes = {Path(j.output).name: j.config_hash for j in batch.jobs}
    assert len(set(hashes.values())) == len(hashes)


def crash_on_spheres(job):
    """A task that kills its worker process for sphere scans (simulates a segfault / OOM kill)."""
    if "sphere" in job.scan.name:
        os._exit(3)
    from splatdeform.batch.worker import process_scan

    return process_scan(job)


def test_worker_crash_fails_only_its_scan(scans: Path) -> None:
    from splatdeform.batch import load_batch
    from splatdeform.batch.runner import run_local

    cfg = write_batch(scans / "crash.yaml", scans="scans/*_00[0-3].ply", output_dir="out_crash")
    jobs = load_batch(cfg).jobs
    assert len(jobs) == 4
    got = {Path(r["scan"]).stem: r for r in run_local(jobs, 2, lambda r: None,
                                                        fn=crash_on_spheres)}
    assert got["sphere_003"]["status"] == "failed"
    assert "worker process died" in got["sphere_003"]["error"]
    assert all(got[k]["status"] == "ok" for k in ("bar_000", "bar_001", "bar_002"))
