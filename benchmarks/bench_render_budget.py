"""``render`` of big LiDAR results within ``--memory-budget``: seconds and peak RSS per scan
size, idle and beside two CPU-busy processes.

    python benchmarks/bench_render_budget.py                     # 25M points, budget 1GB
    python benchmarks/bench_render_budget.py --sizes 1 5 25 --budget 1GB --busy

Scans: ``data_tools.lidar`` (seeded synthetic airborne LAS, point format 1, 28 bytes a point,
no RGB: elevation colours, z up, flat discs with eye-dome lighting), written once per size
into a temporary folder (``--keep DIR`` reuses them). Each render is its own process; its
peak is that process's VmHWM (its own high-water mark; ru_maxrss would carry the parent's).
Target (issue 24): 25M points in <= 30 s with peak RSS <= budget + 300 MB.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

RUN = """
import sys
from splatdeform.cli import main
code = main(sys.argv[1:])
hwm = next(x for x in open("/proc/self/status") if x.startswith("VmHWM"))
print("PEAK", int(hwm.split()[1]) * 1024, code)
"""

BUSY = "while True: pass"


def render(scan: Path, out: Path, budget: str) -> dict:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", RUN, "render", str(scan), "-o", str(out),
                           "--memory-budget", budget], capture_output=True, text=True,
                          cwd=ROOT, check=True)
    seconds = time.perf_counter() - t0
    peak = next(int(x.split()[1]) for x in proc.stdout.splitlines() if x.startswith("PEAK"))
    line = next((x for x in proc.stdout.splitlines() if "rendered" in x), "whole model")
    return {"seconds": round(seconds, 1), "peak_mb": peak // 2**20, "line": line.strip()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--sizes", type=float, nargs="+", default=[25.0],
                        help="scan sizes in millions of points")
    parser.add_argument("--budget", default="1GB")
    parser.add_argument("--busy", action="store_true",
                        help="also measure beside two CPU-busy processes")
    parser.add_argument("--keep", type=Path, help="folder for the scans (kept, reused)")
    args = parser.parse_args()
    from data_tools.lidar import write_lidar

    folder = args.keep or Path(tempfile.mkdtemp(prefix="bench_render_"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        run(args, folder, write_lidar)
    finally:
        if args.keep is None:   # the scans are big: never leave them behind
            shutil.rmtree(folder, ignore_errors=True)


def run(args, folder: Path, write_lidar) -> None:
    rows = []
    for millions in args.sizes:
        n = int(millions * 1e6)
        scan = folder / f"lidar_{n}.las"
        if not scan.exists():
            write_lidar(scan, n)
        loads = ["idle"] + (["busy"] if args.busy else [])
        for load in loads:
            hogs = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(2)] \
                if load == "busy" else []
            try:
                row = render(scan, folder / "out.png", args.budget)
            finally:
                for hog in hogs:
                    hog.kill()
                    hog.wait()
            row.update(points=n, load=load, budget=args.budget)
            rows.append(row)
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
