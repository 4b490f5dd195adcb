"""Control-point pairs (``points:``, issue 36) against scipy's RBFInterpolator.

For 12, 1,000 and 10,000 pairs on a generated terrain (a smooth known warp: a drift growing
along the scan plus two broad bumps, as tests/test_points.py), in one run:

- ours: :func:`splatdeform.deform.points.prepare_points` (``fit.method: auto``: the dense saddle
  solve for small sets, the incremental fit for large ones, pair tolerance 1e-6 of the largest
  pair displacement), then the apply: the basis at every model point (values only) and
  ``values @ delta_c``;
- scipy: ``RBFInterpolator(sources, displacements, kernel="cubic", degree=1)`` (the same
  triharmonic kernel and linear polynomial, a dense solve) and its evaluation at the same
  points.

Each case runs in its own process so that its peak RSS (``ru_maxrss``) is its own. Times are
wall seconds; the largest pair residual (model units) and the RMS difference between the two
fields over the model's points are printed. Run: ``python benchmarks/bench_points.py
[--points 200000] [--pairs 12,1000,10000]``; ``--laz`` adds the streamed ``apply`` of a saved
field to a generated 10M-point LAZ under ``--memory-budget 1GB`` (``--laz-points``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_tools.warps import drift_warp as warp  # noqa: E402 (after the path insert)


def terrain(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) a 2 km x 1 km rolling terrain (metres)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform([0, 0], [1000, 2000], (n, 2))
    z = 20 * np.sin(xy[:, 0] / 170) * np.cos(xy[:, 1] / 230) + 0.01 * xy[:, 1]
    return np.column_stack([xy, z + rng.normal(0, 0.05, n)])


def case(kind: str, n_pairs: int, n_points: int, backend: str = "auto") -> dict:
    """One measured case (in this process): fit and apply seconds, residual, the field."""
    points = terrain(n_points)
    rng = np.random.default_rng(1)
    idx = rng.choice(n_points, n_pairs, replace=False)
    src = points[idx]
    dst = warp(points)[idx]
    out: dict = {"kind": kind, "pairs": n_pairs, "points": n_points}
    if kind == "scipy":
        from scipy.interpolate import RBFInterpolator

        t0 = time.perf_counter()
        rbf = RBFInterpolator(src, dst - src, kernel="cubic", degree=1)
        out["fit_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        disp = rbf(points)
        out["apply_s"] = time.perf_counter() - t0
        out["residual"] = float(np.abs(rbf(src) - (dst - src)).max())
        out["method"] = "dense LU"
    else:
        from splatdeform.basis import resolve_backend
        from splatdeform.deform.deformation import basis_settings, fit_settings
        from splatdeform.deform.points import Pairs, pair_errors, prepare_points
        from splatdeform.model import PointModel

        model = PointModel(positions=points)
        pairs = Pairs(src, dst, [f"pairs[{i}]" for i in range(n_pairs)])
        t0 = time.perf_counter()
        d, pf = prepare_points(model, np.zeros(n_points, bool), [], pairs,
                               fit_fn=fit_settings(model),
                               basis_fn=basis_settings(backend, gradients=False))
        total = time.perf_counter() - t0
        t1 = time.perf_counter()
        disp = d.basis.values.astype(np.float64) @ pf.delta()
        out["fit_s"] = total - d.timings["basis"]   # checks, hull-free set-up and the fit
        out["apply_s"] = d.timings["basis"] + time.perf_counter() - t1
        out["residual"] = float(np.abs(pair_errors(d, pairs, pf.delta())).max())
        out["method"] = f"{d.fit.method}, {d.fit.centers.shape[0]:,} centers, " \
                        f"basis {resolve_backend(backend, None)}"
    np.save(os.environ["BENCH_FIELD"], disp.astype(np.float64))
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def run_case(kind: str, n_pairs: int, n_points: int, tmp: Path, backend: str) -> dict:
    field = tmp / f"{kind}_{n_pairs}.npy"
    env = {**os.environ, "BENCH_FIELD": str(field)}
    proc = subprocess.run([sys.executable, __file__, "--case", kind, "--pairs", str(n_pairs),
                           "--points", str(n_points), "--backend", backend],
                          capture_output=True, text=True, env=env, check=False)
    if proc.returncode:
        raise SystemExit(f"{kind} {n_pairs}: failed\n{proc.stderr[-2000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["field"] = field
    return out


def laz_row(n: int, tmp: Path) -> None:
    """``apply`` of a saved points field to an n-point LAZ under --memory-budget 1GB."""
    from splatdeform.cli import main
    from splatdeform.io import save
    from splatdeform.model import PointModel

    small = terrain(20_000, seed=3)
    save(PointModel(positions=small), tmp / "small.ply")
    rng = np.random.default_rng(2)
    idx = rng.choice(small.shape[0], 30, replace=False)
    rows = ", ".join(str([*map(float, a), *map(float, b)])
                     for a, b in zip(small[idx], warp(small)[idx], strict=True))
    (tmp / "e.yaml").write_text(f"input: small.ply\noutput: small_out.ply\npoints:\n"
                                f"  pairs: [{rows}]\n")
    assert main(["deform", str(tmp / "e.yaml"), "--save-field", str(tmp / "f.npz"),
                 "--quiet"]) == 0
    big = tmp / "big.laz"
    t0 = time.perf_counter()
    save(PointModel(positions=terrain(n, seed=4)), big)
    print(f"generated {n:,}-point LAZ in {time.perf_counter() - t0:.1f} s "
          f"({big.stat().st_size / 2**20:.0f} MiB)")
    t0 = time.perf_counter()
    proc = subprocess.run(["/usr/bin/time", "-v", sys.executable, "-m", "splatdeform.cli", "apply",
                           str(tmp / "f.npz"), str(big), "-o", str(tmp / "out.laz"),
                           "--memory-budget", "1GB"], capture_output=True, text=True,
                          check=False)
    wall = time.perf_counter() - t0
    rss = [ln for ln in proc.stderr.splitlines() if "Maximum resident" in ln]
    print(f"apply {n:,}-point LAZ --memory-budget 1GB: rc {proc.returncode}, {wall:.1f} s, "
          f"peak RSS {int(rss[0].split()[-1]) / 1024:.0f} MB" if rss else proc.stderr[-500:])
    print(proc.stdout.strip())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--case", choices=("ours", "scipy"))
    ap.add_argument("--pairs", default="12,1000,10000")
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--backend", default="auto", help="ours: basis backend (auto: OpenCL "
                    "when present, whose start-up is in the apply time)")
    ap.add_argument("--laz", action="store_true")
    ap.add_argument("--laz-points", type=int, default=10_000_000)
    args = ap.parse_args()
    if args.case:
        out = case(args.case, int(args.pairs), args.points, args.backend)
        print(json.dumps(out))
        return
    import tempfile

    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}; "
          f"{args.points:,} model points")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print(f"{'pairs':>7} {'':6} {'fit s':>8} {'apply s':>8} {'total s':>8} "
              f"{'peak MB':>8} {'max residual m':>15}  method")
        for n in (int(v) for v in args.pairs.split(",")):
            rows = [run_case(k, n, args.points, tmp, args.backend) for k in ("ours", "scipy")]
            for r in rows:
                print(f"{n:>7,} {r['kind']:6} {r['fit_s']:8.3f} {r['apply_s']:8.3f} "
                      f"{r['fit_s'] + r['apply_s']:8.3f} {r['peak_rss_mb']:8.0f} "
                      f"{r['residual']:15.2e}  {r['method']}")
            a, b = rows
            diff = np.load(a["field"]) - np.load(b["field"])
            print(f"{'':>7} ratio  {b['fit_s'] / a['fit_s']:8.1f} "
                  f"{b['apply_s'] / a['apply_s']:8.1f} "
                  f"{(b['fit_s'] + b['apply_s']) / (a['fit_s'] + a['apply_s']):8.1f}   "
                  f"(scipy / ours); RMS field difference "
                  f"{np.sqrt(np.mean(np.sum(diff * diff, axis=1))):.2e} m")
        if args.laz:
            laz_row(args.laz_points, tmp)


if __name__ == "__main__":
    main()
