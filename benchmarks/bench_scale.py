"""Millions of points at the speed of reading them (issue 45's targets): every case as a whole
process against the floor of the same file, ratios taken in one run, with each process's peak RSS.

    python benchmarks/bench_scale.py                    # idle: 5M and 20M
    python benchmarks/bench_scale.py --busy 2           # beside two CPU-bound processes
    python benchmarks/bench_scale.py --sizes 5 --skip laz pcd
    python benchmarks/bench_scale.py --sizes 5 --memory-only --repeat 3   # in-memory 5M alone

Files are generated in a temporary folder (``--workdir`` to keep them between runs), never in
the repository. Scans: the bumpy cylinder of ``bench_stream.py`` (x in [0, 4], binary PLY with
float x y z nx ny nz, seeded). Edit (the usual bend): fixed first 25 % along x, handle last 25 %
rotated 20 degrees about z, C2 rings, default fit, backend auto.

The **floor** is a bare numpy read-modify-write of the same file: ``np.fromfile`` of the vertex
block, one column changed, the header and block written back, interpreter and numpy import
included, as its own process. For LAZ the floor is laspy with lazrs reading and writing the same
file (one column changed). Every case runs as ``python -c WRAP cmd...``: the wrapper times the
child and reads its peak RSS from ``getrusage(RUSAGE_CHILDREN).ru_maxrss`` (the wrapper itself
is ~10 MB, so what ru_maxrss carries over exec is negligible). ``best of --repeat``.

Cases: deform 5M in memory; the same streamed with ``--memory-budget 1GB``; 20M streamed (and
100M if asked with ``--sizes``); 5M LAZ streamed; compressed PCD load against the same points as
binary PLY (load only, timed inside the process); ``convert`` identity PLY->PLY; the paper
table's 270k scene (``bench_e2e``'s bar and edit) as a whole process against its own floor.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

EDIT = {
    "regions": {"units": "relative",
                "fixed": [{"box": {"min": [0, 0, 0], "max": [0.25, 1, 1]}}],
                "handle": [{"box": {"min": [0.75, 0, 0], "max": [1, 1, 1]}}]},
    "handle": {"transform": {"pivot": [0.75, 0.5, 0.5],
                             "rotate": {"axis": [0, 0, 1], "degrees": 20}}},
}

WRAP = """
import resource, subprocess, sys, time
t0 = time.perf_counter()
out = subprocess.run(sys.argv[1:], capture_output=True, text=True)
wall = time.perf_counter() - t0
sys.stdout.write(out.stdout)
sys.stderr.write(out.stderr)
print("#WRAP", out.returncode, wall, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
"""

FLOOR_PLY = """
import sys
import numpy as np
path, out = sys.argv[1], sys.argv[2]
with open(path, "rb") as f:
    head = b""
    while not head.endswith(b"end_header\\n"):
        head += f.readline()
    types = {"float": "f4", "float32": "f4", "double": "f8", "uchar": "u1", "uint8": "u1",
             "char": "i1", "int8": "i1", "short": "i2", "int16": "i2", "ushort": "u2",
             "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4"}
    props = [ln.split() for ln in head.decode().splitlines() if ln.startswith("property")]
    dtype = np.dtype([(p[2], "<" + types[p[1]]) for p in props])
    rows = np.fromfile(f, dtype=dtype)
rows["x"] += 1.0
with open(out, "wb") as f:
    f.write(head)
    rows.tofile(f)
"""

FLOOR_LAZ = """
import sys
import laspy
las = laspy.read(sys.argv[1], laz_backend=laspy.LazBackend.Lazrs)
las.X = las.X + 1
las.write(sys.argv[2], laz_backend=laspy.LazBackend.Lazrs)
"""

LOAD = """
import sys, time
t0 = time.perf_counter()
from splatdeform.io import load
t1 = time.perf_counter()
m = load(sys.argv[1])
print("#LOAD", t1 - t0, time.perf_counter() - t1, m.n_points)
"""

MAKE_LAZ = """
import sys
import laspy
import numpy as np
rows = np.fromfile(sys.argv[1], dtype="<f4", offset=int(sys.argv[3])).reshape(-1, 6)
header = laspy.LasHeader(point_format=0, version="1.2")
header.scales = np.array([1e-4, 1e-4, 1e-4])
header.offsets = np.array([0.0, 0.0, 0.0])
las = laspy.LasData(header)
las.x, las.y, las.z = rows[:, 0], rows[:, 1], rows[:, 2]
las.intensity = (np.arange(len(rows)) % 4096).astype(np.uint16)
las.write(sys.argv[2], laz_backend=laspy.LazBackend.Lazrs)
"""


def _spin(stop) -> None:
    while not stop.is_set():
        pass


def wrapped(cmd: list[str], cwd: Path = ROOT) -> dict:
    """Seconds, peak RSS (MB) and stdout of one process ``cmd``."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = str(ROOT)
    res = subprocess.run([sys.executable, "-c", WRAP, *cmd], capture_output=True, text=True,
                         cwd=cwd, env=env)
    last = res.stdout.strip().splitlines()[-1].split()
    if last[0] != "#WRAP" or last[1] != "0":
        raise SystemExit(f"{' '.join(cmd)} failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}")
    print(f"  {' '.join(cmd[-4:])[-90:]}: {float(last[2]):.2f} s", file=sys.stderr, flush=True)
    return {"s": float(last[2]), "mb": int(last[3]) / 1024, "out": res.stdout + res.stderr}


def best(cmd: list[str], repeat: int, cwd: Path = ROOT) -> dict:
    runs = [wrapped(cmd, cwd) for _ in range(repeat)]
    return min(runs, key=lambda r: r["s"])


def sd(*args: str) -> list[str]:
    return [sys.executable, "-m", "splatdeform.cli", *args]


def py(code: str, *args: str) -> list[str]:
    return [sys.executable, "-c", code, *args]


def header_size(path: Path) -> int:
    with open(path, "rb") as f:
        head = b""
        while not head.endswith(b"end_header\n"):
            head += f.readline()
    return len(head)


def edit_config(folder: Path, scan: Path, out: Path) -> Path:
    cfg = folder / f"{scan.name}_to_{out.name}.yaml"   # the PLY's and the LAZ's apart
    cfg.write_text(yaml.safe_dump(dict(EDIT, input=str(scan), output=str(out))))
    return cfg


def streamed(out: str) -> bool:
    return "pass 5" in out


def run_cases(opts: argparse.Namespace, work: Path) -> list[tuple[str, dict, dict, str]]:
    """(case, ours, floor, note) rows."""
    from bench_stream import write_cylinder

    rows = []
    rep = opts.repeat
    tmp_out = work / "out"
    tmp_out.mkdir(exist_ok=True)

    def clean() -> None:
        for p in tmp_out.iterdir():
            p.unlink()

    for millions in opts.sizes:
        n = int(millions * 1_000_000)
        scan = work / f"cyl_{n}.ply"
        if not scan.exists():
            write_cylinder(scan, n)
        floor = best(py(FLOOR_PLY, str(scan), str(tmp_out / "floor.ply")), rep)
        clean()
        label = f"{millions:g}M"
        if "deform" not in opts.skip and n <= opts.memory_max * 1_000_000:
            cfg = edit_config(work, scan, tmp_out / "bent.ply")
            r = best(sd("deform", str(cfg)), rep)
            clean()
            rows.append((f"deform {label} PLY in memory", r, floor,
                         "streamed!" if streamed(r["out"]) else ""))
        if "deform" not in opts.skip and not opts.memory_only:
            cfg = edit_config(work, scan, tmp_out / "bent.ply")
            r = best(sd("deform", str(cfg), "--memory-budget", opts.budget), rep)
            clean()
            rows.append((f"deform {label} PLY --memory-budget {opts.budget}", r, floor,
                         "" if streamed(r["out"]) else "in memory (estimate under the budget)"))
        # under the budget: stream it anyway
        if "deform" not in opts.skip and not opts.memory_only and not streamed(r["out"]) \
                and n >= 1_000_000:
            r = best(sd("deform", str(cfg), "--memory-budget", "512MB"), rep)
            clean()
            rows.append((f"deform {label} PLY --memory-budget 512MB", r, floor,
                         "" if streamed(r["out"]) else "in memory"))
        if millions == opts.sizes[0]:
            if "convert" not in opts.skip:
                r = best(sd("convert", str(scan), str(tmp_out / "copy.ply")), rep)
                clean()
                rows.append((f"convert {label} PLY->PLY identity", r, floor, ""))
            if "pcd" not in opts.skip:
                pcd = work / f"cyl_{n}.pcd"
                if not pcd.exists():
                    subprocess.run(sd("convert", str(scan), str(pcd), "--pcd-data",
                                      "binary_compressed"), check=True, cwd=ROOT,
                                   capture_output=True)
                got = {}
                for kind, path in (("ply", scan), ("pcd", pcd)):
                    runs = [wrapped(py(LOAD, str(path))) for _ in range(rep)]
                    loads = [float(next(ln for ln in r["out"].splitlines()
                                        if ln.startswith("#LOAD")).split()[2]) for r in runs]
                    got[kind] = (min(loads), min(runs, key=lambda r: r["s"]))
                rows.append((f"load {label} PCD binary_compressed (in-process load; floor: "
                             "the same points as binary PLY)",
                             dict(got["pcd"][1], s=got["pcd"][0]),
                             dict(got["ply"][1], s=got["ply"][0]), "load time only"))
            if "laz" not in opts.skip:
                laz = work / f"cyl_{n}.laz"
                if not laz.exists():
                    subprocess.run(py(MAKE_LAZ, str(scan), str(laz), str(header_size(scan))),
                                   check=True, cwd=ROOT)
                lfloor = best(py(FLOOR_LAZ, str(laz), str(tmp_out / "floor.laz")), rep)
                clean()
                cfg = edit_config(work, laz, tmp_out / "bent.laz")
                r = best(sd("deform", str(cfg), "--memory-budget", opts.budget), rep)
                clean()
                rows.append((f"deform {label} LAZ --memory-budget {opts.budget} (floor: laspy+"
                             "lazrs)", r, lfloor,
                             "" if streamed(r["out"]) else "in memory (estimate under budget)"))
    if "paper" not in opts.skip:
        from bench_e2e import edit_yaml

        from data_tools.synth import bumpy_bar
        from splatdeform.io import save

        folder = work / "paper"
        folder.mkdir(exist_ok=True)
        model = bumpy_bar(270_000, seed=7)
        save(model, folder / "bar.ply")
        edit = edit_yaml(model, folder)
        subprocess.run(sd("deform", str(edit)), check=True, capture_output=True, cwd=folder)
        floor = best(py(FLOOR_PLY, str(folder / "bar.ply"), str(folder / "floor.ply")),
                     max(rep, 3))
        r = best(sd("deform", str(edit)), max(rep, 3), cwd=folder)
        rows.append((f"deform paper scene {model.n_points // 1000}k (bench_e2e's bar)", r,
                     floor, "best of 3"))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[5, 20],
                    help="millions of points (default 5 20; the first also gets convert, "
                         "PCD and LAZ)")
    ap.add_argument("--memory-max", type=float, default=5,
                    help="in-memory deform only up to this many millions (default 5)")
    ap.add_argument("--budget", default="1GB", help="the streamed runs' --memory-budget")
    ap.add_argument("--busy", type=int, default=0, help="CPU-bound processes beside the run")
    ap.add_argument("--repeat", type=int, default=1, help="best of N per case (default 1)")
    ap.add_argument("--skip", nargs="*", default=[],
                    choices=["deform", "convert", "pcd", "laz", "paper"],
                    help="cases left out (deform: the PLY deforms; the floor still runs)")
    ap.add_argument("--memory-only", action="store_true",
                    help="only the in-memory deform case(s) and their floor (no streamed "
                    "runs, convert, PCD, LAZ or paper scene)")
    ap.add_argument("--workdir", help="folder for the generated files (default: a temp dir, "
                    "removed at the end)")
    ap.add_argument("--json", help="also write the rows here")
    opts = ap.parse_args()
    if opts.memory_only:
        opts.skip = sorted({*opts.skip, "convert", "pcd", "laz", "paper"})
    work = Path(opts.workdir or tempfile.mkdtemp(prefix="bench_scale."))
    work.mkdir(parents=True, exist_ok=True)
    print(f"# {time.strftime('%Y-%m-%d %H:%M %Z')} {platform.node()} ({os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f} at start), beside {opts.busy} busy "
          f"processes, python {platform.python_version()}", flush=True)
    stop = multiprocessing.Event()
    procs = [multiprocessing.Process(target=_spin, args=(stop,)) for _ in range(opts.busy)]
    for p in procs:
        p.start()
    try:
        rows = run_cases(opts, work)
    finally:
        stop.set()
        for p in procs:
            p.join()
        if not opts.workdir:
            shutil.rmtree(work, ignore_errors=True)
    print(f"# load average {os.getloadavg()[0]:.1f} at end")
    print("| case | ours s | peak MB | floor s | floor peak MB | ratio | note |")
    print("|---|---|---|---|---|---|---|")
    for case, r, f, note in rows:
        print(f"| {case} | {r['s']:.2f} | {r['mb']:.0f} | {f['s']:.2f} | {f['mb']:.0f} | "
              f"**{r['s'] / f['s']:.1f}x** | {note} |")
    for case, r, _f, _note in rows:  # per-pass lines of the deform runs
        lines = [ln for ln in r["out"].splitlines() if ln.startswith("pass ")
                 or (len(ln.split()) == 3 and ln.split()[2] == "s")]
        if lines:
            print(f"# {case}: " + "; ".join(ln.strip() for ln in lines))
    if opts.json:
        Path(opts.json).write_text(json.dumps(
            [{"case": c, "s": r["s"], "mb": r["mb"], "floor_s": f["s"], "floor_mb": f["mb"],
              "note": note} for c, r, f, note in rows], indent=1))


if __name__ == "__main__":
    main()
