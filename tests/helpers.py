"""Helpers shared by the test modules (no test module imports another test module).

- :func:`run_cli`: the one way tests run the CLI, always in a subprocess with a timeout (a hang
  fails the test instead of blocking the suite); :func:`one_error_line` checks the error
  contract (exit 2, one ``splatdeform: error:`` line, no traceback).
- :func:`base_config` / :func:`write_config`: the one base edit config of the CLI tests (a bar
  along x in model units); ``conftest.bar_edit`` is its relative-units sibling.
- :func:`run_cli_peak` and :func:`load_peaks`: peak resident memory of a child process (its
  VmHWM), which sees every allocator (numpy, lazrs, zlib, Pillow), unlike tracemalloc.
- Synchronisation by polling a condition (:func:`wait_for`), never by sleeping a fixed time.
- Work bounds in CPU seconds (:class:`cpu_time`), never in wall-clock time: a loaded machine
  stretches the second, not the first.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
TIMEOUT = 180   # seconds for one CLI run; every case answers in seconds, a hang took minutes


def run_cli(*args, cwd: Path | str = ROOT, timeout: float = TIMEOUT, env: dict | None = None,
            **kw) -> subprocess.CompletedProcess:
    """``python -m splatdeform.cli ARGS`` in ``cwd``; ``env`` adds to this environment."""
    return subprocess.run([PY, "-m", "splatdeform.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=timeout,
                          env=None if env is None else {**os.environ, **env}, **kw)


def one_error_line(res: subprocess.CompletedProcess, code: int = 2, needles=()) -> str:
    """The one error line of a failed run (exit ``code``, no traceback), containing each of
    ``needles``."""
    assert res.returncode == code, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr + res.stdout, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("splatdeform: error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def base_config(scans: Path, **extra) -> dict:
    """An edit of ``scans/bar.ply`` (a generated bumpy bar along x, model units): the end at
    x <= 1 fixed, x >= 3 the handle, rotated 20 degrees and lifted."""
    return {
        "input": str(scans / "bar.ply"),
        "output": "out/bent.ply",
        "regions": {"units": "model",
                    "fixed": [{"box": {"min": [-1, -1, -1], "max": [1.0, 1, 1]}}],
                    "handle": [{"box": {"min": [3.0, -1, -1], "max": [5, 1, 1]}}]},
        "handle": {"transform": {"rotate": {"axis": [0, 0, 1], "degrees": 20},
                                 "translate": [0, 0.2, 0]}},
        "fit": {"tolerance": 1e-3},
        "backend": "numpy",
        **extra,
    }


def write_config(folder: Path, cfg: dict | str, name: str = "edit.yaml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(cfg if isinstance(cfg, str) else yaml.safe_dump(cfg))
    return path


def snapshot(*folders: Path) -> dict[Path, tuple[int, bytes | None]]:
    """Every entry under the folders: (mode, bytes for regular files)."""
    out = {}
    for folder in folders:
        for p in [folder, *folder.rglob("*")]:
            st = p.lstat()
            out[p] = (st.st_mode, p.read_bytes() if stat.S_ISREG(st.st_mode) else None)
    return out


def dead_pid() -> int:
    """The pid of a process that has exited (for stale-temporary tests)."""
    proc = subprocess.Popen([PY, "-c", "pass"])
    proc.wait(timeout=60)
    return proc.pid


def catches_sigterm(pid: int) -> bool:
    """Whether process ``pid`` has a SIGTERM handler installed (its /proc SigCgt mask)."""
    with contextlib.suppress(OSError):
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return bool(int(line.split()[1], 16) & (1 << (signal.SIGTERM - 1)))
    return False


def wait_for(condition: Callable[[], bool], timeout: float = 60, what: str = "condition",
             poll: float = 0.01) -> None:
    """Poll ``condition`` until it holds; AssertionError naming ``what`` after ``timeout``."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(poll)


class cpu_time:  # noqa: N801 - used as a context manager, like a function
    """CPU seconds (user + system) spent inside a ``with`` block by this process (all its
    threads) and by the children it waited for (``subprocess.run``), in ``.seconds`` after the
    block. Tests bound work with it; a wall-clock bound fails on a loaded machine.

    Example::

        with cpu_time() as cpu:
            run_cli("info", path)
        assert cpu.seconds < 10
    """

    seconds: float = 0.0

    @staticmethod
    def _now() -> float:
        return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                      resource.getrusage(resource.RUSAGE_CHILDREN)))

    def __enter__(self) -> cpu_time:
        self._start = self._now()
        return self

    def __exit__(self, *exc) -> None:
        self.seconds = self._now() - self._start


# -------------------------------------------------------------- peak memory of a child

def vm_hwm_bytes() -> int:
    """This process's peak resident memory (VmHWM) in bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmHWM in /proc/self/status")


# runs the CLI's main in a fresh interpreter and writes its VmHWM (kB) to the file named by the
# first argument, whatever the exit (ru_maxrss would carry the forking parent's peak)
_PEAK_WRAPPER = r"""
import sys
hwm_file = sys.argv.pop(1)
from splatdeform.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
finally:
    status = open("/proc/self/status").read().splitlines()
    open(hwm_file, "w").write(next(ln for ln in status if ln.startswith("VmHWM")).split()[1])
sys.exit(code)
"""


def run_cli_peak(*args, cwd: Path, timeout: float = TIMEOUT,
                 env: dict | None = None) -> tuple[subprocess.CompletedProcess, int]:
    """:func:`run_cli` in a wrapper that measures the child; (result, its peak RSS in bytes)."""
    hwm = Path(cwd) / f".hwm.{os.getpid()}"
    res = subprocess.run([PY, "-c", _PEAK_WRAPPER, str(hwm), *map(str, args)],
                         capture_output=True, text=True, cwd=cwd, timeout=timeout,
                         env=None if env is None else {**os.environ, **env})
    peak = int(hwm.read_text()) * 1024
    hwm.unlink()
    return res, peak


# loads each file given on stdin (one path a line) in this one child, resetting the peak before
# each (Linux: "5" to clear_refs resets VmHWM), and prints one JSON line per file
_LOAD_PEAKS = r"""
import json, sys
import numpy as np
from splatdeform.errors import SplatdeformError
from splatdeform.info import describe, to_json
from splatdeform.io import load

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) * 1024

for path in sys.stdin.read().splitlines():
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    base = status("VmRSS:")
    row = {"path": path}
    try:
        model = load(path)
    except SplatdeformError as exc:
        row["error"] = str(exc)
    except Exception as exc:
        row["escaped"] = f"{type(exc).__name__}: {exc}"
    else:
        row["finite"] = bool(np.isfinite(model.positions).all())
        json.loads(to_json(describe(model)))   # info's strict JSON works on it
        row["points"] = int(model.n_points)
        del model
    row["peak"] = status("VmHWM:") - base
    print(json.dumps(row), flush=True)
"""


def load_peaks(paths: Iterable[Path], timeout: float = 600) -> list[dict]:
    """Load every file in one child process; per file: ``error`` (a SplatdeformError's text) or
    ``escaped`` (any other exception) or ``finite``/``points``, and ``peak``: the bytes its
    load added to the child's resident memory at its highest (VmHWM above the RSS before)."""
    res = subprocess.run([PY, "-c", _LOAD_PEAKS], input="\n".join(map(str, paths)),
                         capture_output=True, text=True, cwd=ROOT, timeout=timeout)
    assert res.returncode == 0, res.stderr[-3000:]
    return [json.loads(line) for line in res.stdout.splitlines()]


# -------------------------------------------------------------------------- batch

def batch_report(out: Path) -> dict[str, dict]:
    """A batch's report.json rows by scan name."""
    return {r["scan"]: r for r in json.loads((out / "report.json").read_text())["scans"]}


def batch_edit() -> dict:
    """The batch tests' edit: ``conftest.bar_edit`` with the handle turned about its inner end
    and at most 200 centers (generated bars fit in well under a second)."""
    from conftest import bar_edit

    return bar_edit({"pivot": [0.75, 0.5, 0.5], "translate": [0, 0.1, 0]},
                    fit={"tolerance": 1e-3, "max_centers": 200})


def write_batch(path: Path, edit: dict | None = None, **keys) -> Path:
    """A batch file of ``edit`` (default :func:`batch_edit`) and the batch ``keys`` (scans,
    output_dir, ...)."""
    path.write_text(yaml.safe_dump({"edit": batch_edit() if edit is None else edit, **keys}))
    return path


# -------------------------------------------------------------------------- LAS files

def make_las(path: Path, version: str = "1.2", fmt: int = 3, n: int = 3000,
             extra: bool = False, evlr: bool = False) -> Path:
    """A small LAS/LAZ (by suffix) of ``n`` points on a bumpy sheet (seeded by the name)."""
    import laspy
    from laspy.vlrs.vlrlist import VLRList

    rng = np.random.default_rng(len(path.name))
    header = laspy.LasHeader(version=version, point_format=fmt)
    if extra:
        header.add_extra_dims([laspy.ExtraBytesParams(name="height", type=np.float32)])
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.array([1000.0, 2000.0, 10.0])
    las = laspy.LasData(header)
    xy = rng.uniform(0, 50, size=(n, 2))
    las.x, las.y = xy[:, 0], xy[:, 1]
    las.z = np.sin(xy[:, 0] / 5) + 0.1 * rng.normal(size=n)
    las.intensity = rng.integers(0, 1000, n).astype(np.uint16)
    if extra:
        las.height = rng.normal(size=n).astype(np.float32)
    if evlr:
        las.evlrs = VLRList([laspy.VLR(user_id="test", record_id=1, description="an evlr",
                                       record_data=b"x" * 100)])
    las.write(path)
    return path
