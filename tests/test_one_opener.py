"""Every file a run reads goes through the one opener (issue 44 item 4): camera files and a
batch's per-scan sidecars are regular files of a bounded size, refused (or, for a sidecar,
ignored: the scan is redone) without blocking on a FIFO or reading a huge file."""

from __future__ import annotations

import json
import os
import re
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


def test_an_indices_file_is_read_through_io(tmp_path):
    """``.NPY`` is a .npy array (io's case-insensitive parser, not ``.suffix == '.npy'``), the
    file goes through the one opener, and an error quotes no more than a short line of it."""
    import numpy as np

    from splatdeform.edit.selectors.indices import Indices, load_indices

    np.save(tmp_path / "p.npy", np.array([3, 1, 2], dtype=np.int32))
    (tmp_path / "p.npy").rename(tmp_path / "P.NPY")
    assert load_indices(Indices(file="P.NPY"), tmp_path).tolist() == [3, 1, 2]
    (tmp_path / "t.txt").write_text("4\n5\n")
    assert load_indices(Indices(file="t.txt"), tmp_path).tolist() == [4, 5]
    (tmp_path / "long.txt").write_text("x" * 5000 + "\n")
    with pytest.raises(InputError, match="long.txt") as info:
        load_indices(Indices(file="long.txt"), tmp_path)
    assert len(str(info.value)) < 300
    os.mkfifo(tmp_path / "f.txt")
    with pytest.raises(InputError, match="f.txt"):
        load_indices(Indices(file="f.txt"), tmp_path)


def test_box_and_plane_rules_are_one_each():
    """A bad box or plane says the same thing from a config and from Python (issue 44)."""
    import numpy as np

    from splatdeform.edit.config import parse_edit
    from splatdeform.edit.selectors.box import Box
    from splatdeform.edit.selectors.plane import Plane
    from splatdeform.errors import ConfigError
    from splatdeform.model import PointModel

    model = PointModel(positions=np.zeros((3, 3)))
    for selector, python, words in [
            ({"box": {"min": [2, 0, 0], "max": [1, 1, 1]}}, Box((2, 0, 0), (1, 1, 1)),
             "exceeds max"),
            ({"plane": {"point": [0, 0, 0], "normal": [0, 0, 0]}},
             Plane((0, 0, 0), (0, 0, 0)), "non-zero vector")]:
        with pytest.raises(ConfigError, match=words):
            parse_edit({"input": "a.ply", "output": "b.ply",
                        "regions": {"fixed": [selector],
                                    "handle": [{"indices": [0]}]},
                        "handle": {"matrix": np.eye(4).tolist()}}, "edit")
        with pytest.raises(InputError, match=words):
            python.mask(model)


@pytest.mark.parametrize("text,key", [("1_0.5", "min[0]"), ("0x10", "min[0]"), ("1:30", "min[0]"),
                                      ("0o17", "min[0]")])
def test_config_numbers_are_read_strictly(tmp_path, text, key):
    """YAML 1.1 reads 1_0.5 as 10.5, 0x10 as 16 and 1:30 as 90; a config number is plain
    decimal, as the PLY reader and pairs files read numbers (issue 43 item 4)."""
    from splatdeform.edit.config import load_edit
    from splatdeform.errors import ConfigError

    path = tmp_path / "e.yaml"
    path.write_text("input: a.ply\noutput: b.ply\nregions:\n  fixed: [{box: {min: [" + text
                    + ", 0, 0], max: [20, 1, 1]}}]\n  handle: [{indices: [0]}]\n"
                    "handle: {matrix: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}\n")
    with pytest.raises(ConfigError, match=re.escape(key) + ".*plain decimal number"):
        load_edit(path)
