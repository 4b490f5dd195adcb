"""One scan on Dask: a real LocalCluster (2 worker processes) deforms the chunks as parts; the
assembled output equals the local streaming output (bit-exact fixed and handle points, free
points within the backend's rounding: worker BLAS runs single-threaded), also when one worker is
killed mid-run (its chunks are recomputed; parts are idempotent)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import distributed
import pytest
import yaml
from conftest import bar_edit
from distributed.diagnostics.plugin import WorkerPlugin
from fixtures import assert_same_result

from data_tools.synth import bumpy_bar
from splatdeform.cli import main
from splatdeform.edit.config import load_edit
from splatdeform.edit.stream import run_stream
from splatdeform.io import save

EDIT = bar_edit({"rotate": {"axis": [0, 0, 1], "degrees": 30}, "translate": [0, 0.1, 0]})
CHUNK = 2_500


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("dask")
    save(bumpy_bar(40_000, seed=9), folder / "bar.ply")
    (folder / "edit.yaml").write_text(yaml.safe_dump(dict(EDIT, input="bar.ply",
                                                          output="local.ply")))
    cfg = load_edit(folder / "edit.yaml")
    run_stream(cfg, folder, chunk=CHUNK, quiet=True)
    return folder, cfg


@pytest.fixture(scope="module")
def client():
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       dashboard_address=None)
    with distributed.Client(cluster) as c:
        yield c
    cluster.close()


def test_dask_equals_local(scene, client) -> None:
    folder, cfg = scene
    result = run_stream(cfg, folder, output=folder / "dask.ply", chunk=CHUNK, quiet=True,
                        client=client)
    assert result.stats["points"] == 40_000
    assert_same_result(folder / "local.ply", folder / "dask.ply", folder / "bar.ply")
    assert not list(folder.glob(".dask.parts.*"))  # part folder removed


class _KillOnFirstPart(WorkerPlugin):
    """Kills its worker (SIGKILL) the moment a part task of the run finishes on it, before the
    scheduler hears of the result, once per ``marker`` file (created exclusively, holding the
    pid). The kill happens inside the run by construction: no watcher thread racing the run."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def transition(self, key, start, finish, **kwargs) -> None:
        if finish != "memory" or not str(key).startswith("splatdeform-part-"):
            return
        try:
            fd = os.open(self.marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL)
        except FileExistsError:
            return  # one kill per run: the nanny's new worker carries the plugin too
        os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        os.kill(os.getpid(), signal.SIGKILL)


def test_dask_survives_a_killed_worker(scene, client) -> None:
    folder, cfg = scene
    marker = folder / "killed.pid"
    client.register_plugin(_KillOnFirstPart(str(marker)), name="kill-on-first-part")
    try:
        run_stream(cfg, folder, output=folder / "killed.ply", chunk=CHUNK // 2, quiet=True,
                   client=client)
    finally:
        client.unregister_worker_plugin("kill-on-first-part")
    assert marker.is_file(), "no part task finished on a worker"
    victim = int(marker.read_text())
    assert victim not in client.run(os.getpid).values()  # killed (its nanny started another)
    assert_same_result(folder / "local.ply", folder / "killed.ply", folder / "bar.ply")


def test_cli_scheduler_address(scene, client) -> None:
    folder, _ = scene
    out = folder / "cli.ply"
    assert main(["deform", str(folder / "edit.yaml"), "-o", str(out), "--scheduler",
                 client.scheduler.address, "--quiet"]) == 0
    assert_same_result(folder / "local.ply", out, folder / "bar.ply")


def test_cli_workers_refuses_unstreamable_input(tmp_path: Path, capsys) -> None:
    save(bumpy_bar(3_000, seed=2), tmp_path / "a.ply", text=True)
    (tmp_path / "e.yaml").write_text(yaml.safe_dump(dict(EDIT, input="a.ply", output="o.ply")))
    assert main(["deform", str(tmp_path / "e.yaml"), "--workers", "2", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "binary PLY" in err and err.count("\n") == 1
    assert not (tmp_path / "o.ply").exists()
