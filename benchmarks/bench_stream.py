"""Streaming ``deform`` on big generated scans: points/s and peak RSS, vs the in-memory path,
and one scan on a 2-worker Dask LocalCluster vs local streaming.

    python benchmarks/bench_stream.py                 # 10M points (in-memory comparison too)
    python benchmarks/bench_stream.py --sizes 10 50 100 --budget 2GB --no-memory-path
    python benchmarks/bench_stream.py --dask           # + Dask 2 workers vs local, at 10M

Scans: a bumpy cylinder (length 4, radius 0.5) as binary little-endian PLY with float x y z
nx ny nz (24 bytes per point), written chunk by chunk (seeded). Edit: fixed left quarter,
handle right quarter rotated 35 degrees and lifted, C2 rings, fit tolerance 1e-3, backend auto
(OpenCL on PoCL here). Each run is its own process; peak RSS is that process's ru_maxrss.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]

EDIT = {
    "regions": {"units": "relative",
                "fixed": [{"box": {"min": [0, 0, 0], "max": [0.25, 1, 1]}}],
                "handle": [{"box": {"min": [0.75, 0, 0], "max": [1, 1, 1]}}]},
    "handle": {"transform": {"pivot": [0.75, 0.5, 0.5],
                             "rotate": {"axis": [0, 0, 1], "degrees": 35},
                             "translate": [0, 0.1, 0]}},
    "fit": {"tolerance": 1e-3},
}

RUN = """
import resource, subprocess, sys, time
t0 = time.perf_counter()
rc = subprocess.call(sys.argv[1:], stdout=subprocess.DEVNULL)
print(rc, time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
"""


def write_cylinder(path: Path, n: int, seed: int = 0, chunk: int = 2_000_000) -> None:
    """n points on a bumpy cylinder with unit normals, binary PLY, written in chunks."""
    rng = np.random.default_rng(seed)
    dtype = np.dtype([(c, "<f4") for c in ("x", "y", "z", "nx", "ny", "nz")])
    with open(path, "wb") as f:
        f.write(f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n".encode())
        for c in dtype.names:
            f.write(f"property float {c}\n".encode())
        f.write(b"end_header\n")
        for start in range(0, n, chunk):
            m = min(chunk, n - start)
            x = rng.uniform(0, 4, m)
            t = rng.uniform(0, 2 * np.pi, m)
            r = 0.5 * (1 + 0.04 * np.sin(5 * t) * np.sin(3 * np.pi * x / 4))
            rows = np.empty(m, dtype=dtype)
            rows["x"], rows["y"], rows["z"] = x, r * np.cos(t), r * np.sin(t)
            rows["nx"], rows["ny"], rows["nz"] = 0.0, np.cos(t), np.sin(t)
            f.write(rows.tobytes())


def run(args: list[str]) -> tuple[int, float, float]:
    """(exit code, seconds, peak RSS in MB) of one splatdeform process."""
    out = subprocess.run([sys.executable, "-c", RUN, sys.executable, "-m", "splatdeform.cli",
                          *args], capture_output=True, text=True, cwd=ROOT, check=True)
    rc, seconds, kb = out.stdout.split()
    return int(rc), float(seconds), int(kb) / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[10],
                        help="millions of points (default 10)")
    parser.add_argument("--budget", default="1GB", help="streaming memory budget")
    parser.add_argument("--no-memory-path", action="store_true",
                        help="skip the in-memory comparison")
    parser.add_argument("--dask", action="store_true",
                        help="also a 2-worker Dask LocalCluster at the first size")
    parser.add_argument("--workdir", help="folder for the generated scans (default: a temp dir)")
    opts = parser.parse_args()
    work = Path(opts.workdir or tempfile.mkdtemp(prefix="bench_stream."))
    work.mkdir(parents=True, exist_ok=True)
    print(f"# {time.strftime('%Y-%m-%d')} {platform.node()} {platform.machine()} "
          f"python {platform.python_version()}")
    rows = []
    for millions in opts.sizes:
        n = int(millions * 1_000_000)
        scan = work / f"cyl_{n}.ply"
        if not scan.exists():
            t0 = time.perf_counter()
            write_cylinder(scan, n)
            print(f"generated {n:,} points in {time.perf_counter() - t0:.1f} s "
                  f"({scan.stat().st_size / 2**20:,.0f} MB)", flush=True)
        cfg = work / "edit.yaml"
        cfg.write_text(yaml.safe_dump(dict(EDIT, input=str(scan), output=str(work / "o.ply"))))
        rc, sec, rss = run(["deform", str(cfg), "-o", str(work / "stream.ply"),
                            "--memory-budget", opts.budget, "--quiet"])
        row = {"points": n, "stream_s": sec, "stream_rss_mb": rss, "rc": rc,
               "stream_mpts": n / sec / 1e6}
        print(f"{n:>12,} points  streaming: {sec:7.1f} s  {n / sec / 1e6:5.2f} M points/s  "
              f"peak RSS {rss:7.0f} MB  (budget {opts.budget}, rc {rc})", flush=True)
        if not opts.no_memory_path and millions == opts.sizes[0]:
            rc, msec, mrss = run(["deform", str(cfg), "-o", str(work / "mem.ply"),
                                  "--memory-budget", "1TB", "--quiet"])
            row.update(memory_s=msec, memory_rss_mb=mrss, ratio=sec / msec)
            print(f"{'':>12}         in memory: {msec:7.1f} s  {n / msec / 1e6:5.2f} M points/s  "
                  f"peak RSS {mrss:7.0f} MB  (rc {rc});  streaming / in-memory time "
                  f"{sec / msec:.2f}x", flush=True)
        if opts.dask and millions == opts.sizes[0]:
            rc, dsec, drss = run(["deform", str(cfg), "-o", str(work / "dask.ply"),
                                  "--memory-budget", opts.budget, "--workers", "2", "--quiet"])
            row.update(dask_s=dsec, dask_ratio=dsec / sec)
            print(f"{'':>12}     Dask 2 workers: {dsec:7.1f} s  {n / dsec / 1e6:5.2f} M points/s"
                  f"  (client RSS {drss:.0f} MB, rc {rc});  Dask / local streaming time "
                  f"{dsec / sec:.2f}x", flush=True)
        rows.append(row)
        for f in ("stream.ply", "mem.ply", "dask.ply"):
            (work / f).unlink(missing_ok=True)
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
