"""The rings stage at scale (issue 45 item 2): the in-memory rings (kd-trees over the border
band only) before and after, and in-memory vs streamed ``deform`` on the same file.

    python benchmarks/bench_rings.py                     # 1M and 5M points
    python benchmarks/bench_rings.py --sizes 1 5 --before HEAD~3 --repeat 3

Scans: bench_stream's bumpy cylinder (binary PLY, x y z nx ny nz float32), written in a
temporary folder (never in the repository). Edit: fixed the first 25 % along x, handle the last
25 % turned 20 degrees (the issue's bend), C2 rings, k = 10.

Printed per size:
- in process: the rings' kNN adjacency (``border_knn_adjacency``, the stage's cost) with this
  checkout and, with ``--before REV``, with ``splatdeform/deform/rings.py`` of REV (the same
  graph is checked), best of ``--repeat``; and in a child process each, the peak RSS the graph
  adds to the loaded, labelled model;
- whole processes: ``deform`` in memory and with ``--memory-budget`` (streamed): the rings
  stage as the CLI reports it (streamed: plus passes 3 and 4, which gather the border set the
  rings run on), the process time and peak RSS, and the ratios in/streamed.
"""

from __future__ import annotations

import argparse
import importlib.util
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_stream import write_cylinder  # noqa: E402

EDIT = {
    "regions": {"units": "relative",
                "fixed": [{"box": {"min": [0, 0, 0], "max": [0.25, 1, 1]}}],
                "handle": [{"box": {"min": [0.75, 0, 0], "max": [1, 1, 1]}}]},
    "handle": {"transform": {"pivot": [0.75, 0.5, 0.5],
                             "rotate": {"axis": [0, 0, 1], "degrees": 20}}},
    "fit": {"tolerance": 1e-3},
    "backend": "numpy",
}

RUN = """
import resource, subprocess, sys, time
t0 = time.perf_counter()
out = subprocess.run(sys.argv[1:], capture_output=True, text=True)
sys.stdout.write(out.stdout + out.stderr)
print("#", out.returncode, time.perf_counter() - t0,
      resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
"""


def run_deform(cfg: Path, extra: list[str]) -> tuple[float, float, float]:
    """(process seconds, peak RSS MB, rings stage seconds) of one ``deform`` process; streamed,
    the rings stage is the rings on the border set plus passes 3 and 4 (which gather it)."""
    out = subprocess.run([sys.executable, "-c", RUN, sys.executable, "-m", "splatdeform.cli",
                          "deform", str(cfg), *extra], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout
    last = out.strip().splitlines()[-1].split()
    if last[1] != "0":
        raise SystemExit(f"deform failed:\n{out}")
    rings = re.search(r"^rings\s+([0-9.]+) s", out, re.M)
    seconds = float(rings.group(1)) if rings else float("nan")
    for step in re.findall(r"^pass [34] \(border [a-z]+\): [0-9,]+ points in ([0-9.]+) s", out,
                           re.M):
        seconds += float(step)
    return float(last[2]), int(last[3]) / 1024, seconds


PEAK = """
import importlib.util, sys
import numpy as np
def hwm():  # this process's peak RSS in kB (ru_maxrss would carry the parent's over exec)
    with open("/proc/self/status") as f:
        return int(next(ln for ln in f if ln.startswith("VmHWM")).split()[1])
from splatdeform.io import load
if sys.argv[2] == "-":
    from splatdeform.deform import rings
else:
    spec = importlib.util.spec_from_file_location("rings_before", sys.argv[2])
    rings = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rings)
pos = load(sys.argv[1]).positions
u = (pos[:, 0] - pos[:, 0].min()) / np.ptp(pos[:, 0])
labels = (u <= 0.25).astype(np.int8) + 2 * (u >= 0.75).astype(np.int8)
before = hwm()
rings.border_knn_adjacency(pos, labels, 10, 4)
print((hwm() - before) / 1024)
"""


def peak_added(ply: Path, module: str) -> float:
    """MB the kNN graph adds to a process's peak RSS (after loading and labelling), with this
    checkout's rings (``module`` "-") or the file ``module``."""
    out = subprocess.run([sys.executable, "-c", PEAK, str(ply), module], capture_output=True,
                         text=True, cwd=ROOT, check=True).stdout
    return float(out.split()[-1])


def old_rings(rev: str):
    """splatdeform/deform/rings.py of ``rev`` as a module (imports resolve to this checkout)."""
    text = subprocess.run(["git", "show", f"{rev}:splatdeform/deform/rings.py"], cwd=ROOT,
                          capture_output=True, text=True, check=True).stdout
    path = Path(tempfile.mkdtemp()) / "rings_before.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("rings_before", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.source_path = str(path)
    return module


def best(fn, repeat: int, *args) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn(*args)
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[1, 5],
                        help="millions of points (default 1 5)")
    parser.add_argument("--before", default=None, help="git revision to compare against")
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--budget", default="1GB", help="streaming memory budget")
    parser.add_argument("--no-process", action="store_true", help="skip the deform processes")
    args = parser.parse_args()

    from splatdeform.deform import rings
    from splatdeform.io import load

    before = old_rings(args.before) if args.before else None
    with open("/proc/loadavg") as f:
        print(f"load average at start: {f.read().split()[0]} ({__import__('os').cpu_count()} "
              "cores)")
    with tempfile.TemporaryDirectory() as tmp:
        for millions in args.sizes:
            n = int(millions * 1_000_000)
            ply = Path(tmp) / f"cyl{n}.ply"
            write_cylinder(ply, n)
            pos = load(ply).positions
            u = (pos[:, 0] - pos[:, 0].min()) / np.ptp(pos[:, 0])
            labels = (u <= 0.25).astype(np.int8) + 2 * (u >= 0.75).astype(np.int8)
            stats: dict = {}
            t_new, adj = best(rings.border_knn_adjacency, args.repeat, pos, labels, 10, 4,
                              stats)
            line = f"{n:>11,} points  rings kNN graph {t_new:6.2f} s  (kd-tree points " \
                   f"{stats['tree_points']:,}, queried {stats['queried']:,})"
            if before is not None:
                t_old, adj_old = best(before.border_knn_adjacency, args.repeat, pos, labels,
                                      10, 4)
                same = (adj != adj_old).nnz == 0
                line += f"  before {t_old:6.2f} s  ({t_old / t_new:.1f}x; same graph: {same})"
            print(line, flush=True)
            del pos, labels, adj
            line = f"{'':>18}peak RSS the kNN graph adds: {peak_added(ply, '-'):.0f} MB"
            if before is not None:
                line += f", before {peak_added(ply, before.source_path):.0f} MB"
            print(line, flush=True)
            if args.no_process:
                continue
            cfg = Path(tmp) / f"edit{n}.yaml"
            cfg.write_text(yaml.safe_dump(dict(EDIT, input=ply.name, output="out.ply")))
            mem = run_deform(cfg, [])
            streamed = run_deform(cfg, ["--memory-budget", args.budget])
            print(f"{'':>18}deform in memory: {mem[0]:6.2f} s, peak {mem[1]:6.0f} MB, rings "
                  f"{mem[2]:.2f} s | streamed ({args.budget}): {streamed[0]:6.2f} s, peak "
                  f"{streamed[1]:6.0f} MB, rings + passes 3-4 {streamed[2]:.2f} s | in/streamed: "
                  f"process {mem[0] / streamed[0]:.2f}, rings {mem[2] / streamed[2]:.2f}",
                  flush=True)
    with open("/proc/loadavg") as f:
        print(f"load average at end: {f.read().split()[0]}")


if __name__ == "__main__":
    main()
