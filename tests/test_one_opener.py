"""Every file a run reads goes through the one opener (issue 44 item 4): camera files and a
batch's per-scan sidecars are regular files of a bounded size, refused (or, for a sidecar,
ignored: the scan is redone) without blocking on a FIFO or reading a huge file."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from splatdeform.batch.config import Job
from splatdeform.batch.sources import Scan
from splatdeform.batch.worker import MAX_SIDECAR_BYTES, read_sidecar
from splatdeform.errors import InputError
from splatdeform.render.camera import MAX_CAMERA_BYTES, load_camera


def _job(tmp_path: Path) -> Job:
    out = tmp_path / "scan_deformed.ply"
    out.write_bytes(b"ply")
    return Job(Scan(str(tmp_path / "scan.ply")), {}, str(tmp_path), str(out), None, None, "h")


def test_a_sidecar_that_matches_is_read(tmp_path):
    job = _job(tmp_path)
    Path(job.sidecar).write_text(json.dumps({"config_hash": "h", "row": {}}))
    assert read_sidecar(job) == {"config_hash": "h", "row": {}}


@pytest.mark.parametrize("kind", ["fifo", "huge", "folder", "binary"])
def test_a_sidecar_that_is_not_ours_is_ignored(tmp_path, kind):
    job = _job(tmp_path)
    side = Path(job.sidecar)
    if kind == "fifo":
        os.mkfifo(side)          # reading it would block until a writer came
    elif kind == "huge":
        with open(side, "wb") as fh:
            fh.truncate(MAX_SIDECAR_BYTES + 1)
    elif kind == "folder":
        side.mkdir()
    else:
        side.write_bytes(b"\xff\xfe" * 100)
    assert read_sidecar(job) is None


@pytest.mark.parametrize("kind", ["fifo", "huge"])
def test_a_camera_file_is_read_through_the_one_opener(tmp_path, kind):
    cam = tmp_path / "c.camera.json"
    if kind == "fifo":
        os.mkfifo(cam)
    else:
        with open(cam, "wb") as fh:
            fh.truncate(MAX_CAMERA_BYTES + 1)
    with pytest.raises(InputError, match="c.camera.json"):
        load_camera(cam)
