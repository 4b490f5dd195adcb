"""Who may drive the editor, and where it may write.

- Access: the server prints a URL with a random token (as notebook servers do). The page and
  every API request must carry it: the page in the URL's ``t`` query parameter, the API
  requests in the ``X-Editor-Token`` header the page sends; a request whose ``Origin`` names
  another site than the one it was sent to (a web page in the user's browser reaching for
  ``http://127.0.0.1:PORT``) is refused even with the token, and so is one whose ``Host``
  header is not this editor's address (:class:`HostRule`: a loopback name or address, the
  ``--host`` value, a name given with ``--allow-host``; DNS rebinding sends the attacker's own
  name). :func:`refusal` is the one check (the page's server, :mod:`.page_server`).
- Saves: :class:`SaveFolder` turns a file *name* typed in the page into a path in the editor's
  working folder; absolute paths, folders, ``..`` and the inputs are refused, and an existing
  file is only replaced when the caller says the user confirmed it. The camera file a PNG
  brings (``NAME.camera.json``) passes the same checks (:meth:`SaveFolder.save_targets`).
"""

from __future__ import annotations

import contextlib
import hmac
import ipaddress
import os
import secrets
import socket
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from ..errors import InputError, SplatdeformError
from ..io.atomic import NAME_MAX, TEMP_EXTRA

LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1", "ip6-localhost")


def new_token() -> str:
    """A fresh random URL-safe token (192 bits)."""
    return secrets.token_urlsafe(24)


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


def request_token(path: str, headers: Mapping[str, str]) -> str | None:
    """The token a request carries (the page's ``X-Editor-Token`` header, else the ``t`` query
    parameter of the printed URL), or None."""
    header = headers.get("X-Editor-Token")
    if header:
        return header
    query = parse_qs(urlsplit(path).query)
    return query["t"][0] if query.get("t") else None


def _host_name(host_header: str) -> str | None:
    """The lower-case name or address of a ``Host`` header (optional port), or None when it is
    not one (empty, a bad port, a user part)."""
    if not host_header or any(c in host_header for c in "@/?#\\ \t") or \
            not host_header.isprintable():
        return None
    try:
        parts = urlsplit(f"//{host_header}")   # raises on a broken [v6] address
        parts.port  # noqa: B018 - raises on a port that is not a number in range
    except ValueError:
        return None
    return (parts.hostname or "").lower() or None


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class HostRule:
    """Which ``Host`` headers reach this editor: a loopback name or address (``localhost``,
    ``127.x.x.x``, ``[::1]``), the address it was bound to (``--host``), the names given with
    ``--allow-host``, any port. Bound to every interface (or another address than loopback),
    an IP address and this machine's own name pass too: a DNS-rebinding page always sends its
    own domain name, never an address, so only names need the list."""

    bind: str = "127.0.0.1"
    names: tuple[str, ...] = ()

    def allows(self, host_header: str) -> bool:
        name = _host_name(host_header)
        if name is None:
            return False
        if is_loopback(name) or name in {n.lower().strip("[]") for n in self.names}:
            return True
        if is_loopback(self.bind):
            return False
        return name == self.bind.lower().strip("[]") or _is_ip(name) or \
            name in _own_names()


def _own_names() -> set[str]:
    """This machine's host name (and its first label), lower case."""
    name = socket.gethostname().lower()
    return {name, name.split(".")[0]} - {""}


def _same_origin(origin: str, host_header: str) -> bool:
    """``Origin`` names the host:port the request was sent to (the page this server served)."""
    try:   # a port that is not a number in range, a broken [v6]: not this editor's origin
        parts = urlsplit(origin)
        target = urlsplit(f"//{host_header}")
        if parts.scheme not in ("http", "https") or not parts.hostname:
            return False
        port = parts.port or (443 if parts.scheme == "https" else 80)
        target_port = target.port or 80
    except ValueError:
        return False
    return (parts.hostname or "").lower() == (target.hostname or "").lower() and \
        port == target_port


def refusal(path: str, headers: Mapping[str, str], token: str,
            hosts: HostRule | None = None) -> str | None:
    """Why this HTTP request is refused, or None to accept it: the ``Host`` header (``hosts``,
    default: loopback only), the ``Origin`` (none, or the same host and port), then the token
    (compared as UTF-8 bytes, in constant time)."""
    rule = hosts or HostRule()
    get_all = getattr(headers, "get_all", None)
    if get_all is not None and any(len(get_all(h) or []) > 1 for h in ("Host", "Origin")):
        return "refused: more than one Host or Origin header"
    host = headers.get("Host", "") or ""
    if not rule.allows(host):
        shown = _host_name(host) or host[:80]
        return (f"refused: Host {shown!r} is not this editor's address (start it with "
                "--allow-host NAME to reach it by that name)")
    origin = headers.get("Origin")
    if origin is not None and not _same_origin(origin, host):
        return f"refused: requests from another site ({origin[:200]}) may not drive the editor"
    given = request_token(path, headers)
    if given is None or not hmac.compare_digest(given.encode("utf-8", "surrogatepass"),
                                                token.encode()):
        return ("refused: open the editor with the URL it printed when it started (the URL "
                "carries its access token)")
    return None


def _check_name(name: str, what: str) -> str:
    if not name.isprintable():
        raise InputError(f"{what} {name!r}: expected a file name of printable characters (no "
                         "newline, tab or other control character)")
    name = name.strip()
    if not name:
        raise InputError(f"{what}: expected a file name, got nothing")
    if "/" in name or "\\" in name or os.path.isabs(name):
        raise InputError(f"{what} {name!r}: expected a file name only (saves go into the save "
                         "folder; no folders, no absolute paths)")
    if name in (".", "..") or name.startswith(".."):
        raise InputError(f"{what} {name!r}: expected a file name, not a folder or '..'")
    if name.startswith("."):
        raise InputError(f"{what} {name!r}: expected a visible file name (not starting "
                         "with '.')")
    if len(os.fsencode(name)) > NAME_MAX - TEMP_EXTRA:
        raise InputError(f"{what} {name[:40]!r}... ({len(os.fsencode(name))} bytes): file "
                         f"name too long (at most {NAME_MAX - TEMP_EXTRA} bytes)")
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
        something else than a file there, outside the folder once links are resolved, or an
        input). Every file a save writes passes here."""
        path = self.root / _check_name(name, what)
        if path.is_symlink() or (path.exists() and not path.is_file()):
            raise InputError(f"{what} {path.name!r}: exists in the save folder and is not a "
                             "plain file (a link, a folder or a device); choose another name")
        try:
            inside = path.resolve().parent == self.root
        except (OSError, RuntimeError):
            inside = False
        if not inside:
            raise InputError(f"{what} {path.name!r}: is not inside the save folder "
                             f"{self.root}; choose another name")
        if path.resolve() in self.inputs or any(
                p.exists() and path.exists() and os.path.samefile(p, path) for p in self.inputs):
            raise InputError(f"{what} {path.name!r}: is an input of this edit; refusing to "
                             "overwrite it (choose another name)")
        return path

    def targets(self, names: Iterable[tuple[str, str]]) -> list[Path]:
        """Paths for (what, name) pairs; two the same are refused."""
        paths = [self.target(name, what) for what, name in names]
        if len(set(paths)) != len(paths):
            raise InputError("save: the model, edit YAML and image (and the image's camera "
                             "file NAME.camera.json) need different names")
        return paths

    def save_targets(self, model: str, edit_yaml: str, image: str) -> list[Path]:
        """The four files a save writes: model, edit YAML, before/after PNG and the PNG's
        camera file (``NAME.camera.json`` beside it, the renderer's rule), each checked by
        :meth:`target`; replacing any that :meth:`existing` lists needs the user's word."""
        from ..render.camera import camera_sidecar

        png = self.target(image, "before/after")
        return self.targets([("model", model), ("edit YAML", edit_yaml),
                             ("before/after", image),
                             ("camera file", camera_sidecar(png).name)])

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


__all__ = ["HostRule", "SaveFolder", "default_save_folder", "exposure_warning",
           "is_loopback", "new_token", "refusal", "request_token"]
