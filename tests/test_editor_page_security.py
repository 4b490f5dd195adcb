"""The WebGL page's saves go through the one save folder (:class:`~splatdeform.editor.security.
SaveFolder`): file names only, never an input, never outside the folder, and an existing file
only after the user confirms; ``edit --host`` other than loopback warns (the token is still
required)."""

from __future__ import annotations

import hashlib
import subprocess
import sys
import time
from pathlib import Path

import pytest

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.editor import EditorController
from splatdeform.editor.session import Session
from splatdeform.errors import InputError


def _tree_hash(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        h.update(str(p.relative_to(folder)).encode())
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


@pytest.fixture()
def work(tmp_path: Path) -> Path:
    (tmp_path / "work").mkdir()
    (tmp_path / "neighbour").mkdir()
    (tmp_path / "neighbour" / "notes.yaml").write_text("keep: me\n")
    sd.save(bumpy_bar(800, seed=3), tmp_path / "work" / "bar.ply")
    return tmp_path


def _fitted(path: Path) -> Session:
    s = Session(EditorController.open(path))
    box = s.ed.model.positions
    lo, hi = box.min(0), box.max(0)
    span = hi - lo
    s.act({"op": "add_selector", "role": "fixed", "kind": "box",
           "center": list((lo + [0.1 * span[0], span[1] / 2, span[2] / 2]) - s.ed.origin),
           "size": list(span * [0.25, 1.2, 1.2])})
    s.act({"op": "add_selector", "role": "handle", "kind": "box",
           "center": list((lo + [0.9 * span[0], span[1] / 2, span[2] / 2]) - s.ed.origin),
           "size": list(span * [0.25, 1.2, 1.2])})
    s.act({"op": "fit"})
    return s


@pytest.mark.parametrize("names", [
    ("/tmp/escaped.ply", "e.yaml", "e.png"),                 # absolute path
    ("../neighbour/escaped.ply", "e.yaml", "e.png"),         # out of the folder
    ("sub/escaped.ply", "e.yaml", "e.png"),                  # a folder
    ("bar.ply", "e.yaml", "e.png"),                          # the input
    ("x.ply", "../neighbour/notes.yaml", "x.png"),
])
def test_page_save_refuses_paths_out_of_the_folder_and_inputs(work, names):
    s = _fitted(work / "work" / "bar.ply")
    before = _tree_hash(work)
    with pytest.raises(InputError) as err:
        s.act({"op": "save", "model": names[0], "yaml": names[1], "png": names[2]})
    assert "\n" not in str(err.value)
    assert _tree_hash(work) == before


def test_page_save_replaces_only_after_confirmation(work):
    s = _fitted(work / "work" / "bar.ply")
    st = s.act({"op": "save", "model": "x.ply", "yaml": "x.yaml", "png": "x.png"})
    assert "wrote" in st["message"] and "confirm" not in st
    first = (work / "work" / "x.ply").read_bytes()
    (work / "work" / "x.ply").write_bytes(b"user's own file")
    # replace without having been asked: asks first, writes nothing
    st = s.act({"op": "save", "model": "x.ply", "yaml": "x.yaml", "png": "x.png",
                "replace": True})
    assert st["confirm"] == ["x.ply", "x.yaml", "x.png", "x.camera.json"]
    assert (work / "work" / "x.ply").read_bytes() == b"user's own file"
    # names changed since the question: asked again
    st = s.act({"op": "save", "model": "x.ply", "yaml": "x.yaml", "png": "y.png",
                "replace": True})
    assert "confirm" in st and (work / "work" / "x.ply").read_bytes() == b"user's own file"
    # confirmed for the same names: replaced
    st = s.act({"op": "save", "model": "x.ply", "yaml": "x.yaml", "png": "y.png",
                "replace": True})
    assert "wrote" in st["message"]
    assert (work / "work" / "x.ply").read_bytes() == first


def test_page_save_dir_and_defaults_are_names(work):
    target = work / "elsewhere"
    target.mkdir()
    from splatdeform.editor.security import default_save_folder

    ed = EditorController.open(work / "work" / "bar.ply")
    s = Session(ed, default_save_folder(ed, target))
    st = s.state()
    assert st["save_folder"] == str(target.resolve())
    assert all("/" not in name for name in st["defaults"])


def test_edit_page_on_every_interface_warns_and_keeps_the_token(work):
    import urllib.error
    import urllib.request

    proc = subprocess.Popen([sys.executable, "-m", "splatdeform.cli", "edit",
                             str(work / "work" / "bar.ply"), "--port", "0", "--host", "0.0.0.0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = None
        deadline = time.time() + 90
        while time.time() < deadline and url is None:
            line = proc.stdout.readline()
            if "http://" in line:
                url = line.split()[2]
        assert url is not None, "the editor printed no URL"
        port = url.split(":")[2].split("/")[0]
        opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
        with pytest.raises(urllib.error.HTTPError) as err:
            opener.open(f"http://127.0.0.1:{port}/api/state", timeout=10)
        assert err.value.code == 403
        assert opener.open(url, timeout=10).status == 200
    finally:
        proc.terminate()
        _, err_text = proc.communicate(timeout=30)
    assert "warning" in err_text and "every network interface" in err_text


def test_page_is_the_default_viewer(work):
    from splatdeform.cli import build_parser

    args = build_parser().parse_args(["edit", str(work / "work" / "bar.ply")])
    assert args.viewer == "page"
