"""The editor's access and saves: the ``edit`` verb (a real subprocess, a real HTTP client)
refuses requests without its URL token or from a foreign ``Origin``, and sets no cookie; the
page's Save writes only file names into the save folder, never over an input (nothing outside
the save folder changes: the neighbours are hashed). ``--host`` other than loopback and the
replace confirmation: tests/test_editor_page_security.py."""

from __future__ import annotations

import hashlib
import shutil
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from fixtures import start_editor
from helpers import run_cli as _cli

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.editor import EditorController
from splatdeform.editor.security import SaveFolder, default_save_folder, refusal
from splatdeform.editor.session import Session
from splatdeform.errors import InputError

N = 2000   # the bar of tests/test_editor.py, with its fixed and handle boxes
FIXED = sd.Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
HANDLE = sd.Box((3.0, -1.0, -1.0), (5.0, 1.0, 1.0))


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    """parent/{work/bar.ply, work/notes.yaml, other/existing.ply, other/notes.yaml, top.txt}."""
    root = tmp_path_factory.mktemp("secure")
    (root / "work").mkdir()
    (root / "other").mkdir()
    sd.save(bumpy_bar(N, seed=5), root / "work" / "bar.ply")
    (root / "work" / "notes.yaml").write_text("mine: 1\n")
    shutil.copy(root / "work" / "bar.ply", root / "other" / "existing.ply")
    (root / "other" / "notes.yaml").write_text("theirs: 1\n")
    (root / "top.txt").write_text("top\n")
    return root


def digests(root: Path, skip: Path | None = None) -> dict[str, str]:
    """sha256 of every file under ``root`` (except under ``skip``), by relative path."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*"))
            if p.is_file() and (skip is None or not p.is_relative_to(skip))}


@pytest.fixture(scope="module")
def editor(tree):
    proc, port, url = start_editor(tree / "work" / "bar.ply")
    yield port, url
    proc.terminate()
    proc.communicate(timeout=30)


def _get(url: str, headers: dict[str, str] | None = None):
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    return opener.open(urllib.request.Request(url, headers=headers or {}), timeout=20)


def test_url_carries_a_token_and_http_without_it_is_refused(editor):
    port, url = editor
    assert "?t=" in url and len(url.split("?t=")[1]) >= 32
    token = url.split("?t=")[1]
    for bad in (f"http://127.0.0.1:{port}/", f"http://127.0.0.1:{port}/?t=wrong",
                f"http://127.0.0.1:{port}/?token={token}", f"http://127.0.0.1:{port}/api/state"):
        with pytest.raises(urllib.error.HTTPError) as info:
            _get(bad)
        assert info.value.code == 403
    for origin in ("http://evil.example", f"http://127.0.0.1:{port + 1}", "null"):
        with pytest.raises(urllib.error.HTTPError) as info:  # tokened, but sent by another site
            _get(url, {"Origin": origin})
        assert info.value.code == 403
    page = _get(url, {"Origin": f"http://127.0.0.1:{port}"})
    assert page.status == 200 and b"<html" in page.read().lower()
    assert page.headers["Set-Cookie"] is None  # the token travels in the URL and a header only
    state = _get(f"http://127.0.0.1:{port}/api/state", {"X-Editor-Token": token})
    assert state.status == 200
    with pytest.raises(urllib.error.HTTPError) as info:  # no cookie is ever taken for it
        _get(f"http://127.0.0.1:{port}/api/state",
             {"Cookie": f"splatdeform-editor-{port}={token}"})
    assert info.value.code == 403


def test_refusal_rules():
    token = "t" * 32
    ok = {"Host": "127.0.0.1:8080", "Origin": "http://127.0.0.1:8080"}
    assert refusal(f"/?t={token}", ok, token) is None
    assert refusal("/", {**ok, "X-Editor-Token": token}, token) is None
    assert refusal("/", {**ok, "Cookie": f"a=b; splatdeform-editor-8080={token}"}, token)
    assert refusal(f"/?token={token}", ok, token)
    assert refusal(f"/?t={token}", {**ok, "Origin": "null"}, token)
    assert refusal(f"/?t={token}x", ok, token)
    assert refusal(f"/?t={token}", {"Host": "127.0.0.1:8080"}, token) is None


# ---- the page's Save (in-process session) ----------------------------------------------
@pytest.fixture()
def session(tree):
    ed = EditorController.open(tree / "work" / "bar.ply")
    ed.add_selector("fixed", FIXED)
    ed.add_selector("handle", HANDLE)
    ed.settings.fit.tolerance = 1e-3
    ed.fit()
    return Session(ed)


def test_saves_go_only_into_the_save_folder_and_never_over_an_input(session, tree):
    work = tree / "work"
    assert session.save_folder.root == work.resolve()
    outside, inside = digests(tree, skip=work), digests(work)
    attempts = [
        (str(tree / "other" / "existing.ply"), "e.yaml", "e.png"),   # absolute
        ("x.ply", str(tree / "other" / "notes.yaml"), "e.png"),     # absolute
        ("../other/existing.ply", "e.yaml", "e.png"),               # ..
        ("x.ply", "..", "e.png"),
        ("x.ply", "e.yaml", "../escaped.png"),
        ("sub/x.ply", "e.yaml", "e.png"),                           # a folder
        ("bar.ply", "e.yaml", "e.png"),                             # the input
        ("x.ply", "x.ply", "e.png"),                                # twice the same
    ]
    for names in attempts:
        for replace in (False, True):
            req = {"op": "save", "model": names[0], "yaml": names[1], "png": names[2],
                   "replace": replace}
            with pytest.raises(InputError):
                session.act(req)
            assert digests(work) == inside, names
    assert digests(tree, skip=work) == outside
    st = session.act({"op": "save", "model": "x.ply", "yaml": "x.yaml", "png": "x.png"})
    assert st["message"].startswith("wrote"), st["message"]
    assert {"x.ply", "x.yaml", "x.png"} <= {p.name for p in work.iterdir()}
    assert digests(tree, skip=work) == outside
    assert digests(work)["bar.ply"] == inside["bar.ply"]


def test_save_folder_checks_names(tmp_path):
    folder = SaveFolder(tmp_path, [tmp_path / "in.ply"])
    assert folder.target("ok.ply", "model") == tmp_path.resolve() / "ok.ply"
    for bad in ("/etc/passwd", "..", "../x", "a/b", "a\\b", ".hidden", "", "in.ply"):
        with pytest.raises(InputError):
            folder.target(bad, "model")
    (tmp_path / "link.ply").symlink_to(tmp_path / "in.ply")
    with pytest.raises(InputError):
        folder.target("link.ply", "model")
    with pytest.raises(InputError, match="save-dir"):
        SaveFolder(tmp_path / "missing")


def test_save_dir_chooses_the_folder(tree, tmp_path):
    ed = EditorController.open(tree / "work" / "bar.ply")
    folder = default_save_folder(ed, tmp_path)
    assert folder.root == tmp_path.resolve()
    assert (tree / "work" / "bar.ply").resolve() in folder.inputs
    run = _cli("edit", str(tree / "work" / "bar.ply"), "--port", "0", "--save-dir",
               str(tmp_path / "missing"))
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1
    assert "--save-dir" in run.stderr and "Traceback" not in run.stderr
