"""Who may drive the editor, and where it may write.

- Access: the server prints a URL with a random token (as notebook servers do). Every HTTP
  request and websocket handshake must carry it, in the ``token`` query parameter or in the
  cookie the first tokened page load sets (``HttpOnly``, ``SameSite=Strict``: the browser sends
  it back to this origin only); a request whose ``Origin`` names another site than the one it
  was sent to (a web page in the user's browser reaching for ``ws://127.0.0.1:PORT``) is refused
  even with the cookie. :func:`refusal` is the one check; :func:`guarded_viser` applies it to
  viser's accept path.
- Saves: :class:`SaveFolder` turns a file *name* typed in the page into a path in the editor's
  working folder; absolute paths, folders, ``..`` and the inputs are refused, and an existing
  file is only replaced when the caller says the user confirmed it.
"""

from __future__ import annotations

import contextlib
import hmac
import ipaddress
import os
import secrets
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from ..errors import InputError, SplatdeformError

LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1", "ip6-localhost")


def new_token() -> str:
    """A fresh random URL-safe token (192 bits)."""
    return secrets.token_urlsafe(24)


def cookie_name(port: int) -> str:
    return f"splatdeform-editor-{port}"


def is_loopback(host: str) -> bool:
    """True when ``host`` (a bind address or name) only reaches this machine."""
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def exposure_warning(host: str, port: int) -> str | None:
    """The warning ``edit --host`` prints for an address other than loopback, else None."""
    if is_loopback(host):
        return None
    where = "every network interface" if host in ("", "0.0.0.0", "::") else host
    return (f"splatdeform edit: warning: listening on {where} (port {port}): anyone who can "
            "reach this machine over the network and has the URL's token can view the model "
            "and write files into the save folder; share the token with care, or use the "
            "default --host 127.0.0.1")


def _cookies(header: str) -> dict[str, str]:
    out = {}
    for part in header.split(";"):
        name, _, value = part.strip().partition("=")
        if name:
            out[name] = value
    return out


def request_token(path: str, headers: Mapping[str, str], port: int) -> str | None:
    """The token a request carries (query parameter first, then the cookie), or None."""
    query = parse_qs(urlsplit(path).query).get("token")
    if query:
        return query[0]
    return _cookies(headers.get("Cookie", "") or "").get(cookie_name(port))


def _same_origin(origin: str, host_header: str) -> bool:
    """``Origin`` names the host:port the request was sent to (the page this server served)."""
    parts = urlsplit(origin)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        return False
    port = parts.port or (443 if parts.scheme == "https" else 80)
    target = urlsplit(f"//{host_header}")
    try:
        target_port = target.port or 80
    except ValueError:
        return False
    return (parts.hostname or "").lower() == (target.hostname or "").lower() and \
        port == target_port


def refusal(path: str, headers: Mapping[str, str], token: str, port: int) -> str | None:
    """Why this HTTP request / websocket handshake is refused, or None to accept it."""
    origin = headers.get("Origin")
    if origin is not None and not _same_origin(origin, headers.get("Host", "") or ""):
        return f"refused: requests from another site ({origin}) may not drive the editor"
    given = request_token(path, headers, port)
    if given is None or not hmac.compare_digest(given.encode(), token.encode()):
        return ("refused: open the editor with the URL it printed when it started (the URL "
                "carries its access token)")
    return None


@contextlib.contextmanager
def guarded_viser(token: str) -> Iterator[None]:
    """While a ``viser.ViserServer`` is constructed in this block, its websocket server checks
    every request with :func:`refusal` before viser sees it (403 otherwise), and a page loaded
    with ``?token=`` gets the token cookie its own websocket then sends. (viser starts serving
    before its constructor returns; the hook is its ``process_request``.)"""
    import websockets.asyncio.server as wss

    original = wss.serve

    def serve(handler: Callable, *args: Any, process_request: Callable | None = None,
              **kwargs: Any) -> Any:
        def guard(connection: Any, request: Any) -> Any:
            port = connection.local_address[1]
            why = refusal(request.path, request.headers, token, port)
            if why is not None:
                return connection.respond(403, why + "\n")
            response = None if process_request is None else process_request(connection,
                                                                            request)
            if response is not None and "token=" in urlsplit(request.path).query:
                response.headers["Set-Cookie"] = (f"{cookie_name(port)}={token}; Path=/; "
                                                  "HttpOnly; SameSite=Strict")
            return response

        return original(handler, *args, process_request=guard, **kwargs)

    wss.serve = serve
    try:
        yield
    finally:
        wss.serve = original


def _check_name(name: str, what: str) -> str:
    name = name.strip()
    if not name:
        raise InputError(f"{what}: expected a file name, got nothing")
    if "\x00" in name or "/" in name or "\\" in name or os.path.isabs(name):
        raise InputError(f"{what} {name!r}: expected a file name only (saves go into the save "
                         "folder; no folders, no absolute paths)")
    if name in (".", "..") or name.startswith(".."):
        raise InputError(f"{what} {name!r}: expected a file name, not a folder or '..'")
    if name.startswith("."):
        raise InputError(f"{what} {name!r}: expected a visible file name (not starting "
                         "with '.')")
    return name


@dataclass
class SaveFolder:
    """The one folder saves go to (resolved), and the input files it must never replace."""

    root: Path
    inputs: list[Path] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.root = Path(self.root).resolve()
        if not self.root.is_dir():
            raise InputError(f"--save-dir {self.root}: expected an existing folder")
        self.inputs = [Path(p).resolve() for p in self.inputs]

    def target(self, name: str, what: str) -> Path:
        """The path of file ``name`` in the folder (InputError: not a plain name, a link or
        something else than a file there, or an input)."""
        path = self.root / _check_name(name, what)
        if path.is_symlink() or (path.exists() and not path.is_file()):
            raise InputError(f"{what} {name!r}: exists in the save folder and is not a plain "
                             "file; choose another name")
        if path.resolve() in self.inputs or any(
                p.exists() and path.exists() and os.path.samefile(p, path) for p in self.inputs):
            raise InputError(f"{what} {name!r}: is an input of this edit; refusing to "
                             "overwrite it (choose another name)")
        return path

    def targets(self, names: Iterable[tuple[str, str]]) -> list[Path]:
        """Paths for (what, name) pairs; two the same are refused."""
        paths = [self.target(name, what) for what, name in names]
        if len(set(paths)) != len(paths):
            raise InputError("save: the model, edit YAML and image need three different names")
        return paths

    @staticmethod
    def existing(paths: Iterable[Path]) -> list[Path]:
        """Those of ``paths`` that exist (replacing them needs the user's confirmation)."""
        return [p for p in paths if p.exists()]


def default_save_folder(controller: Any,
                        save_dir: str | Path | None = None) -> SaveFolder:
    """The save folder (``save_dir``, else the folder of the model or config opened) and the
    edit's inputs, which saves never replace."""
    from ..edit.config import input_paths

    inputs = [controller.model_path, *([controller.config_path] if controller.config_path
                                       else [])]
    with contextlib.suppress(SplatdeformError, AttributeError, TypeError):
        inputs += [p for _, p in input_paths(controller.settings, controller.base_dir)]
    root = save_dir if save_dir is not None else (
        controller.config_path or controller.model_path).parent
    return SaveFolder(Path(root), inputs)


__all__ = ["SaveFolder", "default_save_folder", "exposure_warning", "guarded_viser",
           "is_loopback", "new_token", "refusal", "request_token"]
