"""The page's requests to a running editor server, for tests: :class:`Client` (token header,
JSON actions, strict JSON answers) and :func:`raw` (bytes sent as they are)."""

from __future__ import annotations

import http.client
import json
import socket


def strict_json(body: bytes):
    """The body as JSON, refusing NaN / Infinity (what the page's ``JSON.parse`` accepts)."""
    def refuse(name: str):
        raise AssertionError(f"the answer holds {name}: not valid JSON")

    return json.loads(body, parse_constant=refuse)


def request(port: int, method: str, path: str, *, body: bytes | None = None,
            headers: dict[str, str] | None = None, timeout: float = 60) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        conn.request(method, path, body=body, headers=headers or {})
        resp = conn.getresponse()
        return resp.status, resp.read()
    finally:
        conn.close()


def raw(port: int, data: bytes, timeout: float = 10) -> bytes:
    """Send ``data`` as is, return all the server answers until it closes."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        sock.sendall(data)
        out = b""
        while chunk := sock.recv(65536):
            out += chunk
        return out


class Client:
    """The page's requests to one server (token header, JSON actions)."""

    def __init__(self, port: int, token: str) -> None:
        self.port, self.token = port, token

    def act(self, req: dict | bytes, **headers: str) -> tuple[int, dict]:
        body = req if isinstance(req, bytes) else json.dumps(req).encode()
        status, out = request(self.port, "POST", "/api/action", body=body,
                              headers={"X-Editor-Token": self.token,
                                       "Content-Type": "application/json", **headers})
        return status, strict_json(out)

    def ok(self, req: dict) -> dict:
        status, out = self.act(req)
        assert status == 200, out.get("error")
        return out
