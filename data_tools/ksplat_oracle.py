"""The `.ksplat` tests' file maker: GaussianSplats3D's own converter (npm
``@mkkellogg/gaussian-splats-3d``, pinned, with its ``three`` peer dependency pinned too),
installed from the npm registry into a local cached folder (``.cache/gaussian-splats-3d``,
ignored by git) and driven by ``data_tools/ksplat_convert.mjs`` (a PLY in, a .ksplat out, at a
compression level and SH degree, the alpha removal threshold 0).

Node and npm: the same as splat-transform's (:func:`data_tools.splat_transform.node_bin`).
``python -m data_tools.ksplat_oracle install`` installs (idempotent) and exits non-zero with one
line when it cannot; :func:`convert` makes a file.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from data_tools.splat_transform import OracleMissing, node_bin, npm_install

PACKAGE = "@mkkellogg/gaussian-splats-3d"
VERSION = "0.4.7"          # pinned: the reader's layout notes were learned from this version
THREE = "three"
THREE_VERSION = "0.160.0"  # the package's peer dependency is three >= 0.160
ROOT = Path(__file__).resolve().parent.parent
CACHE = Path(os.environ.get("KSPLAT_ORACLE_DIR", ROOT / ".cache" / "gaussian-splats-3d"))
DRIVER = Path(__file__).resolve().parent / "ksplat_convert.mjs"


def _version(name: str) -> str | None:
    try:
        return json.loads((CACHE / "node_modules" / name / "package.json").read_text())["version"]
    except (OSError, ValueError, KeyError):
        return None


def installed() -> bool:
    return _version(PACKAGE) == VERSION and _version(THREE) == THREE_VERSION


def install() -> None:
    """Install the pinned packages into CACHE unless they are already there."""
    if installed():
        return
    npm_install(CACHE, [f"{PACKAGE}@{VERSION}", f"{THREE}@{THREE_VERSION}"], installed)


def convert(src: str | Path, out: str | Path, level: int, degree: int,
            timeout: float = 600) -> Path:
    """Write ``out`` (.ksplat) from the PLY ``src`` with the library's converter."""
    if not installed():
        raise OracleMissing(f"{PACKAGE}@{VERSION} is not installed in {CACHE}; run "
                            "`make oracle` (or python -m data_tools.ksplat_oracle install)")
    env = {**os.environ, "KSPLAT_ORACLE_MODULES": str(CACHE / "node_modules")}
    proc = subprocess.run([str(node_bin() / "node"), str(DRIVER), str(src), str(out),
                           str(level), str(degree)], env=env, capture_output=True, text=True,
                          timeout=timeout)
    if proc.returncode != 0:
        tail = (proc.stderr.strip() or proc.stdout.strip()).splitlines()[-3:]
        raise RuntimeError(f"ksplat_convert {src} level {level} degree {degree} failed: "
                           f"{' | '.join(tail)}")
    return Path(out)


if __name__ == "__main__":
    if sys.argv[1:] != ["install"]:
        sys.exit("usage: python -m data_tools.ksplat_oracle install")
    try:
        install()
    except OracleMissing as exc:
        sys.exit(f"error: {exc}")
    print(f"{PACKAGE}@{VERSION} with {THREE}@{THREE_VERSION} ready in {CACHE}")
