"""Issue #32, the editor's part: hostile requests to the page's real HTTP server (on
127.0.0.1, in this process or as the ``edit`` verb in a subprocess) get one line and a 4xx,
never a traceback, a hang or a file written outside the save folder.

- Save: the PNG's camera file (``NAME.camera.json``) passes the checks of the three typed
  names (a link is refused, never written through; an existing one needs Replace).
- The server: half-open connections neither pin a thread nor keep a valid request out; a bad
  ``Content-Length`` is a 400/413; NaN / Infinity / 1e400 anywhere in a request is a 400 and
  every answer is valid JSON; at most 64 handles and 1,000 selectors; the ``Host`` header must
  name this editor (DNS rebinding), ``--allow-host`` adds a name; a non-ASCII token is a 403;
  save names are printable.
- Poses: a singular or nearly singular 3x3 part is refused naming the handle (pose and Save).
"""

from __future__ import annotations

import hashlib
import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from editor_client import Client as BaseClient
from editor_client import raw as _raw
from editor_client import request as _request
from editor_client import strict_json as _strict_json
from helpers import cpu_time

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.editor.page_server import EditorHTTPServer, make_server
from splatdeform.editor.security import HostRule

N = 800


class Client(BaseClient):
    """The shared client (tests/editor_client.py) with this file's refusal check."""

    def refused(self, req: dict | bytes, *words: str) -> str:
        status, out = self.act(req)
        assert status == 400, out
        line = out["error"]
        assert "\n" not in line and "Traceback" not in line
        for w in words:
            assert w in line, line
        return line


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("round3")
    (root / "work").mkdir()
    (root / "outside").mkdir()
    sd.save(bumpy_bar(N, seed=3), root / "work" / "bar.ply")
    (root / "outside" / "victim.json").write_text("the user's own file\n")
    return root


@pytest.fixture(scope="module")
def server(tree) -> Iterator[EditorHTTPServer]:
    srv = make_server(tree / "work" / "bar.ply", port=0)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()


@pytest.fixture(scope="module")
def page(server) -> Client:
    """A client whose session has a fixed and a handle region and a current fit."""
    c = Client(server.server_address[1], server.token)
    ed = server.session.ed
    lo, hi = ed.model.bbox()
    span = hi - lo
    mid = (lo + hi) / 2 - ed.origin
    for role, x in (("fixed", 0.1), ("handle", 0.9)):
        center = mid.copy()
        center[0] = (lo[0] + x * span[0]) - ed.origin[0]
        c.ok({"op": "add_selector", "role": role, "kind": "box", "center": list(center),
              "size": list(span * [0.25, 1.2, 1.2])})
    ed.settings.fit.tolerance = 1e-3
    c.ok({"op": "fit"})
    return c


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and not p.is_symlink()}


# ---- save: the camera file is checked like the three names ---------------------------------
def test_camera_file_that_is_a_link_is_refused_never_written_through(page, tree):
    work, outside = tree / "work", tree / "outside"
    link = work / "evil.camera.json"
    link.symlink_to(outside / "victim.json")
    try:
        before_out, before_work = _digest(outside), _digest(work)
        line = page.refused({"op": "save", "model": "evil.ply", "yaml": "evil.yaml",
                             "png": "evil.png"}, "evil.camera.json", "not a plain file")
        assert "camera file" in line
        # asked again with replace: the same refusal, nothing written anywhere
        page.refused({"op": "save", "model": "evil.ply", "yaml": "evil.yaml",
                      "png": "evil.png", "replace": True}, "evil.camera.json")
        assert _digest(outside) == before_out and _digest(work) == before_work
        assert (outside / "victim.json").read_text() == "the user's own file\n"
        assert link.is_symlink()
    finally:
        link.unlink()


def test_existing_camera_file_needs_the_replace_confirmation(page, tree):
    work = tree / "work"
    mine = work / "mine.camera.json"
    mine.write_text("my camera\n")
    try:
        st = page.ok({"op": "save", "model": "mine.ply", "yaml": "mine.yaml",
                      "png": "mine.png"})
        assert st["confirm"] == ["mine.camera.json"]
        assert "mine.camera.json" in st["message"]
        assert mine.read_text() == "my camera\n" and not (work / "mine.ply").exists()
        st = page.ok({"op": "save", "model": "mine.ply", "yaml": "mine.yaml",
                      "png": "mine.png", "replace": True})
        assert "wrote" in st["message"] and "confirm" not in st
        camera = json.loads(mine.read_text())
        assert {"position", "target", "width"} <= set(camera)
    finally:
        for name in ("mine.ply", "mine.yaml", "mine.png", "mine.camera.json"):
            (work / name).unlink(missing_ok=True)


def test_the_camera_file_may_not_be_one_of_the_other_names(page, tree):
    before = _digest(tree)
    page.refused({"op": "save", "model": "a.ply", "yaml": "a.yaml", "png": "x.png"} |
                 {"model": "x.camera.json"}, "different names")
    assert _digest(tree) == before


@pytest.mark.parametrize("name", ["ev\nil.png", "evil.png\n", "a\tb.png", "a\x1bb.png",
                                  "a\x00b.png", "a\u2028b.png"])
def test_save_names_are_printable(page, tree, name):
    before = _digest(tree)
    page.refused({"op": "save", "model": "p.ply", "yaml": "p.yaml", "png": name},
                 "printable")
    assert _digest(tree) == before


# ---- singular poses -------------------------------------------------------------------------
SINGULAR = {
    "zeros": np.zeros((3, 3)),
    "flat": np.diag([1.0, 1.0, 0.0]),
    "tiny": np.diag([1.0, 1.0, 1e-7]),                 # below 1e-6
    "ill-conditioned": np.diag([1e5, 1e5, 2e-5]),      # below 1e-9 of the largest
}


@pytest.mark.parametrize("kind", list(SINGULAR))
def test_singular_pose_is_refused_naming_the_handle(page, server, kind):
    m = np.eye(4)
    m[:3, :3] = SINGULAR[kind]
    before = server.session.ed.handles[0].matrix.copy()
    line = page.refused({"op": "pose", "handle": 0, "matrix": m.tolist(), "commit": True},
                        "handle 0", "handle.matrix", "singular")
    assert "collapse" in line
    assert np.array_equal(server.session.ed.handles[0].matrix, before)
    ok = np.eye(4)
    ok[:3, :3] = np.diag([1.0, 1.0, 2e-6])          # thin but not singular: accepted
    assert page.ok({"op": "pose", "handle": 0, "matrix": ok.tolist()}) == {"ok": 1}
    page.ok({"op": "reset_pose", "handle": 0})


def test_singular_pose_is_refused_at_save(page, server, tree):
    ed = server.session.ed
    with server.lock:
        ed.handles[0].matrix = np.diag([0.0, 0.0, 0.0, 1.0])  # as a loaded state could hold
    try:
        before = _digest(tree)
        page.refused({"op": "save", "model": "s.ply", "yaml": "s.yaml", "png": "s.png"},
                     "handle.matrix", "singular")
        assert _digest(tree) == before
    finally:
        with server.lock:
            ed.handles[0].matrix = np.eye(4)


# ---- request bodies -------------------------------------------------------------------------
@pytest.mark.parametrize("length, code", [("-1", 400), ("abc", 400), ("1e3", 400),
                                          ("12, 12", 400), (str(2 << 20), 413),
                                          ("99999999999999999999999", 400)])
def test_bad_content_length_is_a_short_4xx(server, capfd, length, code):
    port = server.server_address[1]
    answer = _raw(port, (f"POST /api/action HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
                         f"X-Editor-Token: {server.token}\r\nContent-Length: {length}\r\n\r\n"
                         "{}").encode())
    # answered at once: a server that waited for the body would answer 408 after its request
    # timeout (or not before _raw's socket timeout, which fails the test)
    assert answer.startswith(f"HTTP/1.0 {code}".encode()), answer[:200]
    assert "Traceback" not in capfd.readouterr().err


def test_body_over_the_limit_is_413(server):
    port = server.server_address[1]
    body = b'{"op": "fit", "pad": "' + b"x" * (1 << 20) + b'"}'
    status, out = _request(port, "POST", "/api/action", body=body,
                           headers={"X-Editor-Token": server.token})
    assert status == 413 and b"too large" in out


@pytest.mark.parametrize("body", [
    b'{"op": "add_selector", "role": "fixed", "kind": "box", "center": [0, 0, 0], '
    b'"size": [Infinity, 1, 1]}',
    b'{"op": "add_selector", "role": "fixed", "kind": "box", "center": [NaN, 0, 0]}',
    b'{"op": "move_selector", "role": "fixed", "index": 0, "size": [-Infinity, 1, 1]}',
    b'{"op": "add_selector", "role": "fixed", "kind": "box", "size": [1e400, 1, 1]}',
    b'{"op": "add_selector", "role": "fixed", "kind": "box", "size": [1e300, 1, 1]}',
    b'{"op": "add_selector", "role": "fixed", "kind": "sphere", "size": 1e16}',
    b'{"op": "add_selector", "role": "fixed", "kind": "box", "handle": 1' + b"0" * 5000 + b"}",
    b'{"op": "pose", "matrix": [Infinity, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}',
    b'[1, 2]', b'{"op": ', b'\xff\xfe',
])
def test_non_finite_or_huge_numbers_are_refused_and_answers_stay_json(page, server, body):
    before = len(server.session.ed.fixed)
    page.refused(body)  # one line; the answer (state + error) parsed as strict JSON
    assert len(server.session.ed.fixed) == before


def test_selector_typed_as_yaml_with_infinity_is_refused(page, server):
    before = len(server.session.ed.fixed)
    page.refused({"op": "add_selector_text", "role": "fixed",
                  "text": "{box: {min: [-.inf, 0, 0], max: [1, 1, 1]}}"})
    assert len(server.session.ed.fixed) == before
    status, out = _request(server.server_address[1], "GET", "/api/state",
                           headers={"X-Editor-Token": server.token})
    assert status == 200 and _strict_json(out)["selectors"]


# ---- bounded counts -------------------------------------------------------------------------
def test_at_most_64_handles_quickly(page, server):
    from splatdeform.editor.controller import MAX_HANDLES

    ed = server.session.ed
    try:
        with cpu_time() as cpu:   # the server answers in this process's threads
            while len(ed.handles) < MAX_HANDLES:
                page.ok({"op": "add_handle"})
        assert cpu.seconds < 30
        page.refused({"op": "add_handle"}, "at most 64")
        assert len(ed.handles) == MAX_HANDLES
    finally:
        with server.lock:
            del ed.handles[1:]


def test_at_most_1000_selectors(page, server):
    from splatdeform.edit.selectors import Indices
    from splatdeform.editor.controller import MAX_SELECTORS

    ed = server.session.ed
    kept = list(ed.fixed)
    with server.lock:
        total = len(ed.fixed) + sum(len(h.selectors) for h in ed.handles)
        ed.fixed += [Indices((i % N,)) for i in range(MAX_SELECTORS - total - 1)]
    try:
        page.ok({"op": "add_indices", "role": "fixed", "indices": [1, 2]})
        for req in ({"op": "add_indices", "role": "fixed", "indices": [3]},
                    {"op": "add_selector", "role": "handle", "kind": "sphere"},
                    {"op": "add_selector_text", "role": "fixed", "text": "{indices: [4]}"}):
            page.refused(req, "at most 1000")
    finally:
        with server.lock:
            ed.fixed[:] = kept


# ---- who may ask ----------------------------------------------------------------------------
def test_host_header_must_name_this_editor(server):
    port, token = server.server_address[1], server.token
    headers = {"X-Editor-Token": token}
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", "127.0.0.2", f"[::1]:{port}",
                 "LOCALHOST"):
        status, _ = _request(port, "GET", "/api/state", headers={**headers, "Host": host})
        assert status == 200, host
    for host, origin in ((f"evil.com:{port}", f"http://evil.com:{port}"),
                         ("evil.com", "http://evil.com"), (f"evil.com:{port}", None),
                         (f"127.0.0.1.evil.com:{port}", None), ("", None),
                         (f"127.0.0.1:{port}@evil.com", None), ("127.0.0.1:99999", None)):
        h = {**headers, "Host": host} | ({"Origin": origin} if origin else {})
        status, out = _request(port, "GET", "/api/state", headers=h)
        assert status == 403, (host, out)
        status, out = _request(port, "POST", "/api/action", body=b'{"op": "undo"}', headers=h)
        assert status == 403, (host, out)


def test_host_rule():
    loop = HostRule()
    assert loop.allows("localhost:8080") and loop.allows("127.9.9.9") and loop.allows("[::1]")
    assert not loop.allows("evil.com") and not loop.allows("10.0.0.5:8080")
    named = HostRule("127.0.0.1", ("studio.lan",))
    assert named.allows("studio.lan:8080") and named.allows("STUDIO.LAN")
    assert not named.allows("evil.studio.lan")
    every = HostRule("0.0.0.0")
    assert every.allows(f"{socket.gethostname()}:8080") and every.allows("192.168.1.7:8080")
    assert not every.allows("evil.com:8080")
    assert HostRule("192.168.1.7").allows("192.168.1.7:8080")


def test_non_ascii_token_is_403_not_a_traceback(server, capfd):
    port = server.server_address[1]
    for head in (b"X-Editor-Token: \xe9\xe9\r\n", b"X-Editor-Token: \xff\xfe\x80\r\n"):
        answer = _raw(port, b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n" + head + b"\r\n")
        assert answer.startswith(b"HTTP/1.0 403"), answer[:100]
    status, _ = _request(port, "GET", "/api/state?t=%C3%A9%00%ED%A0%80")
    assert status == 403
    for line in (b"GET /?t=\xc3\xa9 HTTP/1.1", b"GET /?t=\xff HTTP/1.1"):
        answer = _raw(port, line + b"\r\nHost: 127.0.0.1\r\n\r\n")
        assert answer.startswith((b"HTTP/1.0 403", b"HTTP/1.0 400")), answer[:100]
    assert "Traceback" not in capfd.readouterr().err


def test_idle_and_partial_connections_are_dropped_after_the_timeout(server):
    port = server.server_address[1]
    server.request_timeout = 1.0
    try:
        socks = [socket.create_connection(("127.0.0.1", port), timeout=10) for _ in range(3)]
        socks[1].sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n")   # no end
        socks[2].sendall(b"POST /api/action HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                         b"Content-Length: 100\r\n\r\n{")                    # short body
        for s in socks:   # each recv fails after the sockets' 10 s if the server keeps it
            while s.recv(4096):  # 408, then closed
                pass
            s.close()
    finally:
        server.request_timeout = 10.0


def test_half_open_connections_keep_no_valid_request_out(tree):
    """The ``edit`` verb with 400 connections that send nothing and 50 with a partial request:
    a valid request is answered within seconds, --allow-host is honoured, and stderr holds no
    traceback (was: ~350 "can't start new thread")."""
    proc = subprocess.Popen([sys.executable, "-m", "splatdeform.cli", "edit",
                             str(tree / "work" / "bar.ply"), "--port", "0",
                             "--allow-host", "studio.lan"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    idle: list[socket.socket] = []
    try:
        url = None
        deadline = time.time() + 60
        while url is None and time.time() < deadline:
            line = proc.stdout.readline()
            if "http://" in line:
                url = line.split()[2]
        assert url is not None, "the editor printed no URL"
        port = int(url.split(":")[2].split("/")[0])
        token = url.split("?t=")[1]
        for i in range(450):
            s = socket.create_connection(("127.0.0.1", port), timeout=10)
            if i >= 400:
                s.sendall(b"POST /api/action HTTP/1.1\r\nContent-Length: 500\r\n\r\n{")
            idle.append(s)
        status, out = _request(port, "GET", "/api/state", timeout=10,   # fails if kept out
                               headers={"X-Editor-Token": token,
                                        "Host": f"studio.lan:{port}"})
        assert status == 200 and "selectors" in _strict_json(out)
        status, _ = _request(port, "GET", "/api/state", timeout=10,
                             headers={"X-Editor-Token": token, "Host": f"other.lan:{port}",
                                      "Origin": f"http://other.lan:{port}"})
        assert status == 403
    finally:
        for s in idle:
            s.close()
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert "Traceback" not in err and "can't start new thread" not in err, err[-2000:]
