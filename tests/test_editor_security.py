"""The editor's access and saves: the ``edit`` verb (a real subprocess, real HTTP and websocket
clients) refuses requests without its URL token or from a foreign ``Origin``; ``--host`` other
than loopback warns and still wants the token; the save handler writes only file names into the
save folder, never over an input, and replaces an existing file only once confirmed (nothing
outside the save folder changes: the neighbours are hashed)."""

from __future__ import annotations

import hashlib
import shutil
import urllib.error
import urllib.request
from pathlib import Path

import pytest
import viser
from test_editor import FIXED, HANDLE, N, _cli, _start_editor
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.editor import EditorController
from splatdeform.editor.security import SaveFolder, refusal
from splatdeform.errors import InputError

PROTOCOL = [f"viser-v{viser.__version__}"]


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
    proc, port, url = _start_editor(tree / "work" / "bar.ply")
    yield port, url
    proc.terminate()
    proc.communicate(timeout=30)


def _get(url: str, headers: dict[str, str] | None = None):
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    return opener.open(urllib.request.Request(url, headers=headers or {}), timeout=20)


def test_url_carries_a_token_and_http_without_it_is_refused(editor):
    port, url = editor
    assert "?token=" in url and len(url.split("?token=")[1]) >= 32
    for bad in (f"http://127.0.0.1:{port}/", f"http://127.0.0.1:{port}/?token=wrong",
                f"http://127.0.0.1:{port}/index.html"):
        with pytest.raises(urllib.error.HTTPError) as info:
            _get(bad)
        assert info.value.code == 403
    with pytest.raises(urllib.error.HTTPError) as info:  # tokened, but sent by another site
        _get(url, {"Origin": "http://evil.example"})
    assert info.value.code == 403
    page = _get(url)
    assert page.status == 200 and b"<html" in page.read().lower()
    cookie = page.headers["Set-Cookie"]
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
    # the page's own later requests carry the cookie instead of the query
    again = _get(f"http://127.0.0.1:{port}/", {"Cookie": cookie.split(";")[0]})
    assert again.status == 200


def test_websocket_without_token_or_from_another_site_is_refused(editor):
    port, url = editor
    token = url.split("?token=")[1]
    ws = f"ws://127.0.0.1:{port}/"
    with pytest.raises(InvalidStatus) as info:  # no token
        connect(ws, subprotocols=PROTOCOL, origin=f"http://127.0.0.1:{port}", open_timeout=20)
    assert info.value.response.status_code == 403
    with pytest.raises(InvalidStatus) as info:  # a page elsewhere, even with the token
        connect(f"{ws}?token={token}", subprotocols=PROTOCOL, origin="http://evil.example",
                open_timeout=20)
    assert info.value.response.status_code == 403
    with pytest.raises(InvalidStatus):  # same host, other port: another site too
        connect(f"{ws}?token={token}", subprotocols=PROTOCOL,
                origin=f"http://127.0.0.1:{port + 1}", open_timeout=20)
    # the page the editor served connects (so the refusals above are about token and origin)
    with connect(f"{ws}?token={token}", subprotocols=PROTOCOL,
                 origin=f"http://127.0.0.1:{port}", open_timeout=20) as conn:
        assert conn.recv(timeout=20)


def test_refusal_rules():
    token = "t" * 32
    ok = {"Host": "127.0.0.1:8080", "Origin": "http://127.0.0.1:8080"}
    assert refusal(f"/?token={token}", ok, token, 8080) is None
    assert refusal("/", {**ok, "Cookie": f"a=b; splatdeform-editor-8080={token}"}, token,
                   8080) is None
    assert refusal("/", {**ok, "Cookie": f"splatdeform-editor-9090={token}"}, token, 8080)
    assert refusal(f"/?token={token}", {**ok, "Origin": "null"}, token, 8080)
    assert refusal(f"/?token={token}x", ok, token, 8080)
    assert refusal(f"/?token={token}", {"Host": "127.0.0.1:8080"}, token, 8080) is None


def test_host_other_than_loopback_warns_and_still_wants_the_token(tree):
    proc, port, url = _start_editor(tree / "work" / "bar.ply", "--host", "0.0.0.0")
    try:
        with pytest.raises(urllib.error.HTTPError) as info:
            _get(f"http://127.0.0.1:{port}/")
        assert info.value.code == 403
        assert _get(url).status == 200
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        out = proc.stdout.read()  # not communicate(): lines the URL search buffered count too
    assert "warning: listening on every network interface" in out and "token" in out


# ---- the save handler (in-process app) -------------------------------------------------
@pytest.fixture()
def app(tree):
    from splatdeform.editor.server import EditorApp

    ed = EditorController.open(tree / "work" / "bar.ply")
    ed.add_selector("fixed", FIXED)
    ed.add_selector("handle", HANDLE)
    ed.settings.fit.tolerance = 1e-3
    ed.fit()
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    application = EditorApp(ed, server)
    yield application
    application.close()
    server.stop()


def test_saves_go_only_into_the_save_folder_and_never_over_an_input(app, tree):
    work = tree / "work"
    assert app.save_folder.root == work.resolve()
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
            status = app.save_names(*names, replace=replace)
            assert not status.startswith("wrote"), (names, status)
            assert digests(work) == inside
    assert digests(tree, skip=work) == outside
    assert app.save_names("x.ply", "x.yaml", "x.png").startswith("wrote")
    assert {"x.ply", "x.yaml", "x.png"} <= {p.name for p in work.iterdir()}
    assert digests(tree, skip=work) == outside
    assert digests(work)["bar.ply"] == inside["bar.ply"]


def test_replacing_an_existing_file_needs_confirmation(app, tree):
    work = tree / "work"
    before = (work / "notes.yaml").read_text()
    app.out_model.value, app.out_yaml.value, app.out_png.value = "n.ply", "notes.yaml", "n.png"
    app._save()
    assert "exists already: notes.yaml" in app.status_md.content
    assert app.replace_button.visible
    assert (work / "notes.yaml").read_text() == before and not (work / "n.ply").exists()
    app.out_yaml.value = "notes2.yaml"   # names changed: the confirmation no longer holds
    app._save(replace=True)
    assert not app.status_md.content.startswith("wrote notes.yaml")
    assert (work / "notes.yaml").read_text() == before
    app.out_yaml.value = "notes.yaml"
    app._save()
    app._save(replace=True)              # the user pressed 'replace existing'
    assert app.status_md.content.startswith("wrote"), app.status_md.content
    assert (work / "notes.yaml").read_text() != before
    assert not app.replace_button.visible


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
    from splatdeform.editor.server import default_save_folder

    ed = EditorController.open(tree / "work" / "bar.ply")
    folder = default_save_folder(ed, tmp_path)
    assert folder.root == tmp_path.resolve()
    assert (tree / "work" / "bar.ply").resolve() in folder.inputs
    run = _cli("edit", str(tree / "work" / "bar.ply"), "--port", "0", "--save-dir",
               str(tmp_path / "missing"))
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1
    assert "--save-dir" in run.stderr and "Traceback" not in run.stderr
