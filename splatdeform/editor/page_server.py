"""HTTP for the editor's own WebGL2 page (``splatdeform edit``): static files from ``web/``
(page, shaders, the vendored three.js), the model and basis as raw little-endian arrays, and
JSON actions handled by :class:`~splatdeform.editor.session.Session`.

The page deforms on its GPU: the basis goes over once per fit (``/api/basis``), a pose is a
``pose`` action of 16 floats. Loopback by default; every ``/api`` request carries the random
token of the printed URL, and a request whose ``Origin`` is another site is refused.
"""

from __future__ import annotations

import json
import mimetypes
import secrets
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlparse

import numpy as np

from ..resources import resource_path
from . import payload
from .controller import EditorController
from .foreground import serve_until, stop_on_signals
from .security import default_save_folder, exposure_warning, new_token
from .session import Session, error_line

WEB = Path(__file__).with_name("web")
SHARED_SHADERS = ("covariance.glsl",)  # served from shaders/ itself: one source for both stages
MAX_BODY = 1 << 20


class EditorHTTPServer(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, address: tuple[str, int], session: Session) -> None:
        super().__init__(address, _Handler)
        self.session = session
        self.token = new_token()
        self.lock = threading.Lock()
        normals, source = payload.display_normals(session.ed)  # PCA at most once
        self.arrays = payload.model_arrays(session.ed, normals)
        self.scene = payload.scene_info(session.ed, self.arrays, source)

    def url(self) -> str:
        host, port = self.server_address[:2]
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{shown}:{port}/?t={self.token}"


class _Handler(BaseHTTPRequestHandler):
    server: EditorHTTPServer

    def log_message(self, *args: Any) -> None:  # quiet
        pass

    def _send(self, code: int, body: bytes, ctype: str) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, data: Any, code: int = 200) -> None:
        self._send(code, json.dumps(data).encode(), "application/json")

    def _allowed(self) -> bool:
        origin = self.headers.get("Origin")
        host = self.headers.get("Host", "")
        if origin is not None and urlparse(origin).netloc != host:
            return False
        query = parse_qs(urlparse(self.path).query)
        token = self.headers.get("X-Editor-Token") or (query.get("t") or [""])[0]
        return secrets.compare_digest(token, self.server.token)

    def do_GET(self) -> None:  # noqa: N802
        path = urlparse(self.path).path
        if path == "/" or path.startswith("/api/"):
            if not self._allowed():
                self._send(403, b"forbidden: open the URL the editor printed", "text/plain")
                return
        if path == "/":
            self._static("index.html")
        elif path.startswith("/web/shared/") and path[12:] in SHARED_SHADERS:
            self._send(200, resource_path("shaders", path[12:]).read_bytes(), "text/plain")
        elif path.startswith("/web/"):
            self._static(path[5:])
        elif path == "/api/scene":
            self._json(self.server.scene)
        elif path == "/api/state":
            with self.server.lock:
                self._json(self.server.session.state())
        elif path.startswith("/api/array/"):
            a = self.server.arrays.get(path[11:])
            if a is None:
                self._send(404, b"no such array", "text/plain")
            else:
                self._send(200, np.ascontiguousarray(a).tobytes(), "application/octet-stream")
        elif path == "/api/labels":
            with self.server.lock:
                body = self.server.session.labels().tobytes()
            self._send(200, body, "application/octet-stream")
        elif path == "/api/basis":
            with self.server.lock:
                try:
                    body = self.server.session.basis().tobytes()
                except Exception as exc:  # noqa: BLE001 - one line back to the page
                    self._json({"error": error_line(exc)}, 409)
                    return
            self._send(200, body, "application/octet-stream")
        else:
            self._send(404, b"not found", "text/plain")

    def do_POST(self) -> None:  # noqa: N802
        if urlparse(self.path).path != "/api/action" or not self._allowed():
            self._send(403, b"forbidden", "text/plain")
            return
        n = int(self.headers.get("Content-Length") or 0)
        if n > MAX_BODY:
            self._send(413, b"too large", "text/plain")
            return
        try:
            req = json.loads(self.rfile.read(n))
            with self.server.lock:
                out = self.server.session.act(req)
        except Exception as exc:  # noqa: BLE001 - one line back to the page
            with self.server.lock:
                state = self.server.session.state()
            state["error"] = error_line(exc)
            self._json(state, 400)
            return
        self._json(out)

    def _static(self, rel: str) -> None:
        target = (WEB / rel).resolve()
        if not target.is_relative_to(WEB.resolve()) or not target.is_file():
            self._send(404, b"not found", "text/plain")
            return
        ctype = mimetypes.guess_type(target.name)[0] or "application/octet-stream"
        if target.suffix in (".js", ".mjs"):
            ctype = "text/javascript"
        elif target.suffix in (".glsl", ".vert", ".frag"):
            ctype = "text/plain"
        self._send(200, target.read_bytes(), ctype)


def make_server(path: str | Path, host: str = "127.0.0.1", port: int = 8080,
                save_dir: str | Path | None = None) -> EditorHTTPServer:
    """Load MODEL or EDIT.yaml and bind the page's server (the next free port when ``port``
    is taken; 0: any free port). Saves go into ``save_dir`` (default: the folder of the file
    opened), by file name only."""
    controller = EditorController.open(path)
    session = Session(controller, default_save_folder(controller, save_dir))
    for p in ([port] if port == 0 else range(port, min(port + 20, 65536))):
        try:
            return EditorHTTPServer((host, p), session)
        except OSError:
            continue
    return EditorHTTPServer((host, 0), session)


def run(path: str, *, host: str = "127.0.0.1", port: int = 8080,
        save_dir: str | Path | None = None, ready: threading.Event | None = None) -> int:
    """Serve the page, print its URL (with its token), block until Ctrl-C / SIGTERM; returns
    0. An address other than loopback prints a warning naming the exposure."""
    server = make_server(path, host, port, save_dir)
    warning = exposure_warning(host, server.server_address[1])
    if warning:
        print(warning, file=sys.stderr, flush=True)
    with stop_on_signals() as stop:
        thread = threading.Thread(target=server.serve_forever, name="editor-http", daemon=True)
        thread.start()
        try:
            print(f"splatdeform editor: {server.url()}  ({server.session.ed.model.n_points:,} "
                  "points; Ctrl-C to stop)", flush=True)
            serve_until(stop, ready)
        finally:
            server.shutdown()
            server.server_close()
    print("splatdeform editor: stopped", flush=True)
    return 0
