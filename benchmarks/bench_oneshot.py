"""The basis + apply stage of a big bend: the stored basis (B for every free point, then
P + B delta_c) against one-shot evaluation (d(x) and J(x) from the centers and W delta_c, chunk
by chunk), on OpenCL and the numpy reference, with each variant's peak RSS (issue 45 item 1).

    python benchmarks/bench_oneshot.py                       # 1M and 5M points
    python benchmarks/bench_oneshot.py --sizes 1 --backends opencl

Scan: the bumpy cylinder of ``bench_stream.py`` (x in [0, 4], binary PLY, float x y z nx ny nz,
seeded), edit: fixed first 25 % along x, handle last 25 % rotated 20 degrees about z, C2 rings,
default fit. The rings and the fit run once per size (a child process that pickles the
deformation); each variant then runs in its own child process: load the PLY and the pickle,
open the OpenCL device and build its kernel (not timed), then time the stage; peak RSS is that
child's ru_maxrss, printed with the RSS it had before the stage. The floor is a bare numpy
read-modify-write of the same file (np.fromfile, one column changed, tofile) in a child too.
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


def _prepare(scan: Path, out: Path) -> None:
    """Child: rings and fit once, the deformation (basis deferred) pickled."""
    import pickle

    from splatdeform.edit import plain
    from splatdeform.edit.plan import plan_edit
    from splatdeform.edit.run import precompute, prepare_model

    plan = plan_edit(dict(EDIT, input=scan.name, output="unused.ply", backend="numpy"),
                     scan.parent)
    model = prepare_model(plan.cfg, scan.parent, {})
    d = precompute(plan.cfg, model, scan.parent, stored=False)
    delta, matrix = plain.control_displacement(plan.cfg, model, d)
    with open(out, "wb") as f:
        pickle.dump((d, delta, matrix), f, protocol=pickle.HIGHEST_PROTOCOL)
    print(json.dumps({"free": int(d.free_idx.size), "centers": int(d.fit.n_centers)}))


def _measure(scan: Path, prep: Path, backend: str, mode: str) -> None:
    """Child: one variant of the stage, timed, with RSS before and peak."""
    import pickle
    import resource

    import splatdeform as sd
    from splatdeform.basis.oneshot import DeferredBasis

    model = sd.load(scan)
    with open(prep, "rb") as f:
        d, delta, matrix = pickle.load(f)
    d.basis = DeferredBasis(d.basis.points, d.fit, backend, None, True)
    if backend == "opencl":  # device and kernel ready (warm-up's job in deform)
        from splatdeform.basis import opencl

        opencl.prepare_device(None, 3 if mode == "oneshot" else d.k)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    if mode == "stored":
        d.basis.store()
    t1 = time.perf_counter()
    sd.apply(d, model, delta, moving_matrix=matrix)
    t2 = time.perf_counter()
    print(json.dumps({"basis_s": t1 - t0, "apply_s": t2 - t1, "stage_s": t2 - t0,
                      "rss_before_mb": rss0,
                      "rss_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))


def _floor(scan: Path, out: Path) -> None:
    """Child: the bare numpy read-modify-write of the scan (header copied, x shifted)."""
    t0 = time.perf_counter()
    import numpy as np

    raw = scan.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    rows = np.frombuffer(raw, dtype="<f4", offset=end).reshape(-1, 6).copy()
    rows[:, 0] += 1.0
    with open(out, "wb") as f:
        f.write(raw[:end])
        rows.tofile(f)
    print(json.dumps({"floor_s": time.perf_counter() - t0}))


def _child(*args: str) -> dict:
    res = subprocess.run([sys.executable, __file__, "--child", *args], capture_output=True,
                         text=True, cwd=ROOT)
    if res.returncode != 0:
        raise RuntimeError(res.stderr[-3000:])
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        kind, *rest = sys.argv[2:]
        {"prepare": _prepare, "measure": _measure, "floor": _floor}[kind](
            *([Path(rest[0]), Path(rest[1])] + rest[2:]))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[1, 5],
                        help="millions of points (default 1 5)")
    parser.add_argument("--backends", nargs="+", default=["opencl", "numpy"],
                        choices=["opencl", "numpy"])
    parser.add_argument("--workdir", help="folder for the generated scans (default: a temp dir)")
    opts = parser.parse_args()
    from bench_stream import write_cylinder

    work = Path(opts.workdir or tempfile.mkdtemp(prefix="bench_oneshot."))
    work.mkdir(parents=True, exist_ok=True)
    print(f"# {time.strftime('%Y-%m-%d %H:%M')} {platform.node()} {platform.machine()} "
          f"python {platform.python_version()}")
    rows = []
    for millions in opts.sizes:
        n = int(millions * 1_000_000)
        scan = work / f"cyl_{n}.ply"
        if not scan.exists():
            write_cylinder(scan, n)
        prep = work / f"prep_{n}.pkl"
        info = _child("prepare", str(scan), str(prep))
        floor = _child("floor", str(scan), str(work / "floor.ply"))["floor_s"]
        (work / "floor.ply").unlink(missing_ok=True)
        print(f"{n:,} points: {info['free']:,} free, {info['centers']} centers; "
              f"floor (numpy read-modify-write, process) {floor:.2f} s", flush=True)
        for backend in opts.backends:
            got = {mode: _child("measure", str(scan), str(prep), backend, mode)
                   for mode in ("stored", "oneshot")}
            s, o = got["stored"], got["oneshot"]
            print(f"  {backend:6s} stored: basis {s['basis_s']:6.2f} s + apply "
                  f"{s['apply_s']:6.2f} s = {s['stage_s']:6.2f} s, peak RSS "
                  f"{s['rss_peak_mb']:6.0f} MB (before {s['rss_before_mb']:.0f})", flush=True)
            print(f"  {backend:6s} one-shot:                      {o['stage_s']:6.2f} s, peak "
                  f"RSS {o['rss_peak_mb']:6.0f} MB (before {o['rss_before_mb']:.0f});  stored / "
                  f"one-shot time {s['stage_s'] / o['stage_s']:.2f}x, stage peak above load "
                  f"{s['rss_peak_mb'] - s['rss_before_mb']:.0f} -> "
                  f"{o['rss_peak_mb'] - o['rss_before_mb']:.0f} MB; one-shot / floor "
                  f"{o['stage_s'] / floor:.1f}x", flush=True)
            rows.append({"points": n, "backend": backend, "floor_s": floor, **{
                f"{mode}_{key}": value for mode, r in got.items() for key, value in r.items()}})
        prep.unlink(missing_ok=True)
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
