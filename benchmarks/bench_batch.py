"""Batch throughput: scans per minute, serial vs 2 local worker processes vs a 2-worker Dask
LocalCluster, on generated bumpy bars (the configs/bend_bar.yaml edit, no thumbnails).

    python benchmarks/bench_batch.py [--scans 20] [--points 200000] [--backend auto]

Every mode starts from empty outputs (--force semantics) and includes its process start-up;
the ratio column is each mode's throughput over the serial one, measured in the same run.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from data_tools.make_archive import make_scans  # noqa: E402
from splatdeform.batch import run_batch  # noqa: E402


def _batch(root: Path, name: str, backend: str) -> Path:
    edit = yaml.safe_load((ROOT / "configs" / "bend_bar.yaml").read_text())
    for key in ("input", "output", "render"):
        edit.pop(key, None)
    edit["backend"] = backend
    cfg = root / f"{name}.yaml"
    cfg.write_text(yaml.safe_dump({"scans": "scans/*.ply", "edit": edit,
                                   "output_dir": f"out_{name}"}))
    return cfg


def _timed(label: str, cfg: Path, n: int, **kw) -> tuple[str, float, dict]:
    t0 = time.perf_counter()
    summary = run_batch(cfg, force=True, quiet=True, **kw)
    dt = time.perf_counter() - t0
    if summary["counts"]["ok"] != n:
        raise SystemExit(f"{label}: {summary['counts']} (expected {n} ok)")
    return label, dt, summary


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=int, default=20)
    parser.add_argument("--points", type=int, default=200_000)
    parser.add_argument("--backend", default="auto", choices=("auto", "numpy", "opencl"))
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)

    root = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    try:
        t0 = time.perf_counter()
        make_scans(root, args.scans, args.points, spheres=False, zip_name=None)
        print(f"generated {args.scans} scans of ~{args.points:,} points in "
              f"{time.perf_counter() - t0:.1f} s ({root})")
        results = [_timed("serial (1 worker process)", _batch(root, "serial", args.backend),
                          args.scans, workers=1)]
        results.append(_timed(f"{args.workers} local worker processes",
                              _batch(root, "local", args.backend), args.scans,
                              workers=args.workers))
        from distributed import LocalCluster

        with LocalCluster(n_workers=args.workers, processes=True, threads_per_worker=1,
                          dashboard_address=None) as cluster:
            results.append(_timed(f"Dask LocalCluster, {args.workers} workers",
                                  _batch(root, "dask", args.backend), args.scans,
                                  scheduler=cluster.scheduler_address))
        serial = results[0][1]
        rows = results[0][2]["rows"]
        mean = {k: sum(r["timings"].get(k, 0) for r in rows) / len(rows)
                for k in ("load", "rings", "fit", "basis", "apply", "save")}
        print(f"\nbatch of {args.scans} scans x ~{args.points:,} points, backend "
              f"{args.backend}; serial per-scan stages: "
              + ", ".join(f"{k} {v:.2f} s" for k, v in mean.items()))
        print(f"{'mode':<34}{'wall s':>9}{'scans/min':>11}{'vs serial':>11}")
        for label, dt, _ in results:
            print(f"{label:<34}{dt:9.1f}{60 * args.scans / dt:11.1f}{serial / dt:10.2f}x")
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
