"""Issue #43 item 7c, the editor's part: header parsing of the page's real HTTP server.

An ``Origin`` whose port is not a number is a 403 (it was no answer at all), two ``Host`` (or
``Origin``) headers are a 400 (the first one decided), and a Save name longer than a file name
may be is one line and a 400 (it was an internal OSError).
"""

from __future__ import annotations

import email.message
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from editor_client import Client, raw

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.editor.page_server import EditorHTTPServer, make_server
from splatdeform.editor.security import SaveFolder, refusal
from splatdeform.errors import InputError


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[EditorHTTPServer]:
    root = tmp_path_factory.mktemp("headers")
    sd.save(bumpy_bar(300, seed=4), root / "bar.ply")
    srv = make_server(root / "bar.ply", port=0)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()


def _status(answer: bytes) -> int:
    assert answer.startswith(b"HTTP/"), answer[:200]
    return int(answer.split(b" ", 2)[1])


def _get(server: EditorHTTPServer, path: str, *headers: str) -> bytes:
    port = server.server_address[1]
    head = "".join(f"{h}\r\n" for h in headers)
    return raw(port, f"GET {path} HTTP/1.1\r\n{head}Connection: close\r\n\r\n".encode())


@pytest.mark.parametrize("origin", ["http://127.0.0.1:abc", "http://127.0.0.1:99999",
                                    "http://127.0.0.1:-1", "http://[::1:80"])
def test_origin_with_a_bad_port_is_403(server, origin):
    port = server.server_address[1]
    answer = _get(server, "/api/state", f"Host: 127.0.0.1:{port}", f"Origin: {origin}",
                  f"X-Editor-Token: {server.token}")
    assert _status(answer) == 403, answer[:300]
    assert b"another site" in answer


@pytest.mark.parametrize("host", ["[::1", "127.0.0.1:x", "[::1]:99999"])
def test_a_broken_host_header_is_403(server, host):
    answer = _get(server, f"/api/state?t={server.token}", f"Host: {host}")
    assert _status(answer) == 403, answer[:300]


@pytest.mark.parametrize("path", ["/api/state", "/", "/web/index.html"])
@pytest.mark.parametrize("header", ["Host", "Origin"])
def test_two_host_or_origin_headers_are_400(server, path, header):
    port = server.server_address[1]
    good = f"127.0.0.1:{port}" if header == "Host" else f"http://127.0.0.1:{port}"
    other = "evil.example" if header == "Host" else "http://evil.example"
    host = [] if header == "Host" else [f"Host: 127.0.0.1:{port}"]
    for pair in ([good, other], [other, good], [good, good]):
        answer = _get(server, f"{path}?t={server.token}", *host,
                      *(f"{header}: {v}" for v in pair), f"X-Editor-Token: {server.token}")
        assert _status(answer) == 400, answer[:300]
        assert f"more than one {header} header".encode() in answer
    # one of each still works
    answer = _get(server, f"{path}?t={server.token}", f"Host: 127.0.0.1:{port}",
                  f"X-Editor-Token: {server.token}")
    assert _status(answer) == 200


def test_refusal_counts_repeated_headers():
    msg = email.message.Message()
    msg["Host"] = "127.0.0.1:8080"
    msg["Host"] = "evil.example"
    assert "more than one" in refusal("/?t=x", msg, "x")


@pytest.mark.parametrize("which", ["model", "yaml", "png"])
def test_a_300_character_save_name_is_one_line(server, which):
    c = Client(server.server_address[1], server.token)
    names = {"model": "a.ply", "yaml": "a.yaml", "png": "a.png"}
    ext = Path(names[which]).suffix
    names[which] = "n" * (300 - len(ext)) + ext
    before = sorted(p.name for p in server.session.save_folder.root.iterdir())
    status, out = c.act({"op": "save", **names})
    assert status == 400, out
    line = out["error"]
    assert "\n" not in line and "internal" not in line and "too long" in line, line
    assert len(line) < 300
    assert sorted(p.name for p in server.session.save_folder.root.iterdir()) == before


def test_save_names_fit_with_their_temporary_file(tmp_path):
    """The longest name accepted leaves room for the temporary file beside it (and a PNG's
    camera file name is judged too)."""
    folder = SaveFolder(tmp_path)
    assert folder.target("a" * 219 + ".ply", "model").name.endswith(".ply")
    with pytest.raises(InputError, match="too long"):
        folder.target("a" * 220 + ".ply", "model")
    with pytest.raises(InputError, match="camera file .* too long"):
        folder.save_targets("m.ply", "m.yaml", "p" * 215 + ".png")
