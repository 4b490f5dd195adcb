"""HTTP for the editor's own WebGL2 page (``splatdeform edit``): static files from ``web/``
(page, shaders, the vendored three.js), the model and basis as raw little-endian arrays, and
JSON actions handled by :class:`~splatdeform.editor.session.Session`.

The page deforms on its GPU: the basis goes over once per fit (``/api/basis``), a pose is a
``pose`` action of 16 floats. Loopback by default; every ``/api`` request carries the random
token of the printed URL and is checked by :func:`~splatdeform.editor.security.refusal` (the
``Host`` header, the ``Origin``, the token), the editor's one check.

Hostile clients: a connection is only given a worker thread once its whole request (head and
``Content-Length`` body) has arrived; until then one reader thread buffers it, and drops it
:data:`REQUEST_TIMEOUT` seconds after it connected, or when more than :data:`MAX_PENDING`
connections wait (the oldest first). Requests are answered by :data:`WORKERS` threads, with at
most :data:`MAX_QUEUED` waiting (503 beyond); heads are at most :data:`MAX_HEAD` bytes, bodies
at most :data:`MAX_BODY` (413), a ``Content-Length`` that is not a whole number is a 400, and
so are two ``Host`` or two ``Origin`` headers. Every answer is valid JSON (no NaN / Infinity),
and so must every request be.
"""

from __future__ import annotations

import contextlib
import mimetypes
import re
import selectors
import socket
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from http.server import BaseHTTPRequestHandler, HTTPServer
from io import BytesIO
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import numpy as np

from ..resources import resource_path
from . import payload
from .budget import check_budget
from .controller import EditorController
from .foreground import serve_until, stop_on_signals
from .security import HostRule, default_save_folder, exposure_warning, new_token, refusal
from .session import Session, dumps, error_line, parse_request

WEB = Path(__file__).with_name("web")
SHARED_SHADERS = ("covariance.glsl",)  # served from shaders/ itself: one source for both stages
MAX_BODY = 1 << 20          # bytes of one request body
MAX_HEAD = 64 << 10         # bytes of a request line and headers
REQUEST_TIMEOUT = 10.0      # seconds from connecting to a complete request; also each send
MAX_PENDING = 128           # connections whose request is still arriving
WORKERS = 8                 # threads answering complete requests
MAX_QUEUED = 64             # complete requests waiting for (or in) a worker
_LENGTH = re.compile(rb"^content-length[ \t]*:[ \t]*(.*?)[ \t]*\r?$", re.I | re.M)


def declared_length(head: bytes) -> int | None:
    """The body length a request head declares when it is one well-formed ``Content-Length``
    within :data:`MAX_BODY` (0 without one); None otherwise (the handler answers 400/413)."""
    found = _LENGTH.findall(head)
    if not found:
        return 0
    if len(found) > 1 or not re.fullmatch(rb"[0-9]{1,9}", found[0]):
        return None
    n = int(found[0])
    return n if n <= MAX_BODY else None


def _request_end(buf: bytes | bytearray) -> int | None:
    """Bytes of the complete request at the start of ``buf`` (head + declared body), or None
    while more is needed. A head past :data:`MAX_HEAD` raises ValueError."""
    end = buf.find(b"\r\n\r\n")
    end = end + 4 if end >= 0 else -1
    if end < 0:
        lf = buf.find(b"\n\n")
        end = lf + 2 if lf >= 0 else -1
    if end < 0 or end > MAX_HEAD:
        if end > MAX_HEAD or len(buf) > MAX_HEAD:
            raise ValueError("request head too large")
        return None
    n = declared_length(bytes(buf[:end]))
    if n is None:
        return end  # complete as far as we read: the handler refuses the length
    return end + n if len(buf) >= end + n else None


class _Writer:
    """``wfile`` of a handler: every write sent whole (the socket's timeout bounds each send)."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock

    def write(self, data: bytes) -> int:
        self._sock.sendall(data)
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass


def _drain(sock: socket.socket, limit: int = 2 * MAX_BODY, seconds: float = 2.0) -> None:
    """After refusing a body unread: stop sending, then read (and drop) what the client still
    sends, briefly, so that closing does not reset the connection before it read the answer."""
    sock.shutdown(socket.SHUT_WR)
    end = time.monotonic() + seconds
    while limit > 0 and (left := end - time.monotonic()) > 0:
        sock.settimeout(left)
        chunk = sock.recv(1 << 16)
        if not chunk:
            return
        limit -= len(chunk)


class _Pending:
    __slots__ = ("addr", "buf", "deadline", "sock")

    def __init__(self, sock: socket.socket, addr: Any, deadline: float) -> None:
        self.sock, self.addr, self.deadline, self.buf = sock, addr, deadline, bytearray()


class _Reader:
    """One thread buffering requests until complete, then a bounded pool answering them (see
    the module docstring)."""

    def __init__(self, server: EditorHTTPServer) -> None:
        self.server = server
        self.selector = selectors.DefaultSelector()
        self.pending: dict[socket.socket, _Pending] = {}  # oldest first
        self.new: list[tuple[socket.socket, Any]] = []
        self.lock = threading.Lock()
        self.queued = 0
        self.wake_r, self.wake_w = socket.socketpair()
        self.wake_r.setblocking(False)
        self.wake_w.setblocking(False)
        self.selector.register(self.wake_r, selectors.EVENT_READ)
        self.pool = ThreadPoolExecutor(WORKERS, thread_name_prefix="editor-http")
        self.closed = False
        self.thread = threading.Thread(target=self._loop, name="editor-http-reader",
                                       daemon=True)
        self.thread.start()

    def add(self, sock: socket.socket, addr: Any) -> None:
        with self.lock:
            self.new.append((sock, addr))
        with contextlib.suppress(OSError):
            self.wake_w.send(b"\0")

    def close(self) -> None:
        self.closed = True
        with contextlib.suppress(OSError):
            self.wake_w.send(b"\0")
        self.thread.join(5)
        self.pool.shutdown(wait=False, cancel_futures=True)

    def _loop(self) -> None:
        try:
            while not self.closed:
                wait = min((p.deadline for p in self.pending.values()), default=None)
                timeout = 1.0 if wait is None else min(max(wait - time.monotonic(), 0), 1.0)
                for key, _ in self.selector.select(timeout):
                    if key.fileobj is self.wake_r:
                        with contextlib.suppress(OSError):
                            self.wake_r.recv(4096)
                    else:
                        try:
                            self._read(key.fileobj)  # type: ignore[arg-type]
                        except Exception:  # noqa: BLE001 - one bad connection, not the loop
                            self._drop(key.fileobj)  # type: ignore[arg-type]
                self._take_new()
                self._expire()
        finally:
            for sock in list(self.pending):
                self._drop(sock)
            self.selector.close()
            self.wake_r.close()
            self.wake_w.close()

    def _take_new(self) -> None:
        with self.lock:
            new, self.new = self.new, []
        limit = self.server.request_timeout
        for sock, addr in new:
            sock.setblocking(False)
            self.pending[sock] = _Pending(sock, addr, time.monotonic() + limit)
            self.selector.register(sock, selectors.EVENT_READ)
        while len(self.pending) > MAX_PENDING:  # the oldest waiting connection goes
            self._drop(next(iter(self.pending)))

    def _expire(self) -> None:
        now = time.monotonic()
        for sock in [s for s, p in self.pending.items() if p.deadline <= now]:
            self._drop(sock, b"408 Request Timeout")

    def _drop(self, sock: socket.socket, status: bytes | None = None) -> None:
        self.pending.pop(sock, None)
        with contextlib.suppress(KeyError, ValueError):
            self.selector.unregister(sock)
        if status is not None:
            with contextlib.suppress(OSError):
                sock.send(b"HTTP/1.0 " + status + b"\r\nContent-Length: 0\r\n"
                          b"Connection: close\r\n\r\n")
        with contextlib.suppress(OSError):
            sock.close()

    def _read(self, sock: socket.socket) -> None:
        p = self.pending.get(sock)
        if p is None:
            return
        try:
            chunk = sock.recv(1 << 16)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            chunk = b""
        if not chunk:
            self._drop(sock)
            return
        p.buf += chunk
        try:
            end = _request_end(p.buf)
        except ValueError:
            self._drop(sock, b"431 Request Header Fields Too Large")
            return
        if end is not None:
            self._dispatch(p, bytes(p.buf[:end]))

    def _dispatch(self, p: _Pending, data: bytes) -> None:
        self.pending.pop(p.sock, None)
        self.selector.unregister(p.sock)
        with self.lock:
            busy = self.queued >= MAX_QUEUED
            if not busy:
                self.queued += 1
        if busy:
            self._drop(p.sock, b"503 Service Unavailable")
            return
        p.sock.setblocking(True)
        p.sock.settimeout(self.server.request_timeout)
        try:
            self.pool.submit(self._answer, p.sock, p.addr, data)
        except RuntimeError:  # closing
            with self.lock:
                self.queued -= 1
            self._drop(p.sock)

    def _answer(self, sock: socket.socket, addr: Any, data: bytes) -> None:
        try:
            handler = _Handler((sock, data), addr, self.server)
            if handler.unread:
                _drain(sock)
        except OSError:
            pass  # the client went away or stopped reading: nothing to answer
        except Exception as exc:  # noqa: BLE001 - one line, never a traceback
            print(f"splatdeform editor: {error_line(exc)}", file=sys.stderr, flush=True)
        finally:
            with self.lock:
                self.queued -= 1
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_WR)
            with contextlib.suppress(OSError):
                sock.close()


class EditorHTTPServer(HTTPServer):
    """The page's server: accepts connections on its ``serve_forever`` thread and hands them
    to :class:`_Reader` (see the module docstring). ``allow_hosts``: more names the ``Host``
    header may give (``--allow-host``)."""

    request_queue_size = 128
    request_timeout = REQUEST_TIMEOUT

    def __init__(self, address: tuple[str, int], session: Session,
                 allow_hosts: tuple[str, ...] = ()) -> None:
        super().__init__(address, _Handler)
        self.session = session
        self.token = new_token()
        self.hosts = HostRule(address[0], tuple(allow_hosts))
        self.lock = threading.Lock()
        normals, source = payload.display_normals(session.ed)  # PCA at most once
        self.arrays = payload.model_arrays(session.ed, normals)
        self.scene = payload.scene_info(session.ed, self.arrays, source)
        self.reader = _Reader(self)

    def url(self) -> str:
        host, port = self.server_address[:2]
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{shown}:{port}/?t={self.token}"

    def process_request(self, request: Any, client_address: Any) -> None:
        self.reader.add(request, client_address)

    def handle_error(self, request: Any, client_address: Any) -> None:
        exc = sys.exc_info()[1]
        if exc is not None and not isinstance(exc, OSError):
            print(f"splatdeform editor: {error_line(exc)}", file=sys.stderr, flush=True)

    def server_close(self) -> None:
        super().server_close()
        self.reader.close()


class _Handler(BaseHTTPRequestHandler):
    server: EditorHTTPServer
    unread = False  # a body was refused before it was read (drained before closing)

    def setup(self) -> None:
        self.connection, data = self.request
        self.rfile = BytesIO(data)
        self.wfile = _Writer(self.connection)  # type: ignore[assignment]

    def finish(self) -> None:
        self.rfile.close()

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
        try:
            body = dumps(data)
        except ValueError:  # a non-finite number: never invalid JSON to the page
            code, body = 500, dumps({"error": "internal error: the editor state holds a "
                                              "non-finite number"})
        self._send(code, body, "application/json")

    def _refused(self, api: bool) -> bool:
        """Answer 403 and return True when the request may not go on: the ``Host`` always, the
        Origin and token for the page and the API (static files need no token). Two ``Host``
        (or ``Origin``) headers are a 400: which one counts would be a guess."""
        for name in ("Host", "Origin"):
            if len(self.headers.get_all(name) or []) > 1:
                self._send(400, f"bad request: more than one {name} header".encode(),
                           "text/plain; charset=utf-8")
                return True
        if api:
            why = refusal(self.path, self.headers, self.server.token, self.server.hosts)
        elif not self.server.hosts.allows(self.headers.get("Host", "") or ""):
            why = "refused: the Host header is not this editor's address"
        else:
            why = None
        if why is not None:
            self._send(403, f"forbidden: {why}".encode(), "text/plain; charset=utf-8")
        return why is not None

    def do_GET(self) -> None:  # noqa: N802
        path = urlparse(self.path).path
        if self._refused(path == "/" or path.startswith("/api/")):
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

    def _body(self) -> bytes | None:
        """The request body, or None after answering 400 / 411 / 413 for its length."""
        lengths = self.headers.get_all("Content-Length") or []
        self.unread = True
        if self.headers.get("Transfer-Encoding"):
            self._send(411, b"Content-Length required (no Transfer-Encoding)", "text/plain")
            return None
        if len(lengths) > 1 or (lengths and not re.fullmatch(r"[0-9]{1,20}", lengths[0])):
            self._send(400, b"Content-Length: expected one whole number of bytes",
                       "text/plain")
            return None
        n = int(lengths[0]) if lengths else 0
        if n > MAX_BODY:
            self._send(413, f"request body too large (at most {MAX_BODY} bytes)".encode(),
                       "text/plain")
            return None
        self.unread = False
        body = self.rfile.read(n)
        if len(body) != n:
            self._send(400, b"request body shorter than its Content-Length", "text/plain")
            return None
        return body

    def do_POST(self) -> None:  # noqa: N802
        if urlparse(self.path).path != "/api/action":
            self._send(404, b"not found", "text/plain")
            return
        if self._refused(True):
            return
        body = self._body()
        if body is None:
            return
        try:
            req = parse_request(body)
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
                save_dir: str | Path | None = None,
                allow_hosts: tuple[str, ...] = (),
                memory_budget: str | int | None = None) -> EditorHTTPServer:
    """Load MODEL or EDIT.yaml and bind the page's server (the next free port when ``port``
    is taken; 0: any free port). Saves go into ``save_dir`` (default: the folder of the file
    opened), by file name only. ``allow_hosts``: names the ``Host`` header may give besides
    loopback and ``host`` (``--allow-host``). ``memory_budget``: ``--memory-budget``; a
    model over the budget is refused before it is read (:func:`.budget.check_budget`)."""
    check_budget(path, memory_budget)
    controller = EditorController.open(path)
    session = Session(controller, default_save_folder(controller, save_dir))
    for p in ([port] if port == 0 else range(port, min(port + 20, 65536))):
        try:
            return EditorHTTPServer((host, p), session, allow_hosts)
        except OSError:
            continue
    return EditorHTTPServer((host, 0), session, allow_hosts)


def run(path: str, *, host: str = "127.0.0.1", port: int = 8080,
        save_dir: str | Path | None = None, ready: threading.Event | None = None,
        allow_hosts: tuple[str, ...] = (), memory_budget: str | int | None = None) -> int:
    """Serve the page, print its URL (with its token), block until Ctrl-C / SIGTERM; returns
    0. An address other than loopback prints a warning naming the exposure."""
    server = make_server(path, host, port, save_dir, tuple(allow_hosts), memory_budget)
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
