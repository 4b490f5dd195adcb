"""Fits at m = 4k, 20k and 50k constraints (big scans have big rings): time, centers, memory.

Each scene is a generated bumpy bar whose fixed and handle rings hold m/2 constraint points each
(bands three kNN spacings wide, as C2 rings of a dense scan would be), fitted on the handle's
affine coordinates M at the default tolerance. Each size runs in its own subprocess so the peak
RSS (ru_maxrss) is that fit's own; the exact dense solve (scipy) is timed where it fits in
memory and time (m <= 20k).

    python benchmarks/bench_fit_scale.py [--sizes 4000,20000,50000] [--exact-max 20000]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def scene(m: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (m, 3), M (m, 4), delta_c (4, 3)): two ring bands of a bumpy bar along z."""
    rng = np.random.default_rng(seed)
    half = m // 2
    area = 2 * np.pi * 0.15 * 1.0  # side area of the whole bar
    spacing = np.sqrt(area / (m * 60))  # the scan is ~60x denser than its rings
    band = 3 * spacing

    def bar(n: int, z_lo: float, z_hi: float) -> np.ndarray:
        t = rng.uniform(0.0, 2 * np.pi, n)
        z = rng.uniform(z_lo, z_hi, n)
        rad = 0.15 * (1.0 + 0.08 * np.sin(3 * t) * np.sin(8 * z))
        return np.column_stack([rad * np.cos(t), rad * np.sin(t), z])

    fixed = bar(half, 0.3 - band, 0.3)
    handle_ring = bar(m - half, 0.7, 0.7 + band)
    handle_far = bar(2000, 0.7 + band, 1.0)
    c0 = np.vstack([handle_ring, handle_far]).mean(axis=0)
    frame = np.vstack([c0, c0 + [0.3, 0, 0], c0 + [0, 0.3, 0], c0 + [0, 0, 0.3]])
    lhs = np.vstack([frame.T, np.ones(4)])
    rhs = np.zeros((m, 4))
    rhs[half:] = np.linalg.solve(lhs, np.vstack([handle_ring.T, np.ones(len(handle_ring))])).T
    a = np.deg2rad(30.0)
    rot = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    delta = (frame - c0) @ rot.T + c0 + np.array([0.05, 0.1, 0.0]) - frame
    return np.vstack([fixed, handle_ring]), rhs, delta


def one(m: int, exact: bool) -> dict[str, float]:
    """Run in a subprocess: fit one size, report figures as JSON."""
    from splatdeform.rbf import fit_incremental

    pts, rhs, _ = scene(m)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    fit = fit_incremental(pts, rhs)
    t_fit = time.perf_counter() - t0
    out = {"m": m, "centers": fit.n_centers, "fit_s": t_fit, "max_r": fit.max_error,
           "rms_r": fit.rms_error, "converged": fit.converged,
           "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "scene_mib": base / 1024}
    if exact:
        from scipy.interpolate import RBFInterpolator

        t0 = time.perf_counter()
        RBFInterpolator(pts, rhs, kernel="cubic", degree=1)
        out["scipy_s"] = time.perf_counter() - t0
        out["peak_with_scipy_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", default="4000,20000,50000")
    ap.add_argument("--exact-max", type=int, default=20_000)
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--exact", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one, args.exact)))
        return
    print(f"fit scale {time.strftime('%Y-%m-%d')} on {platform.node()} ({os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}); default tolerance, greedy centers, 1 BLAS "
          "thread in our fit; scipy at its default threads")
    print(f"{'m':>7}{'centers':>9}{'fit s':>9}{'max|r|':>10}{'rms|r|':>10}{'peak MiB':>10}"
          f"{'scipy s':>9}{'scipy/ours':>11}{'peak w/ scipy':>14}")
    for m in (int(s) for s in args.sizes.split(",")):
        cmd = [sys.executable, __file__, "--one", str(m)]
        if m <= args.exact_max:
            cmd.append("--exact")
        r = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout)
        sp = r.get("scipy_s")
        print(f"{m:>7,}{r['centers']:>9}{r['fit_s']:>9.3f}{r['max_r']:>10.2e}{r['rms_r']:>10.2e}"
              f"{r['peak_mib']:>10.0f}{'-' if sp is None else format(sp, '.2f'):>9}"
              f"{'-' if sp is None else format(sp / r['fit_s'], '.1f') + 'x':>11}"
              f"{r.get('peak_with_scipy_mib', float('nan')):>14.0f}", flush=True)


if __name__ == "__main__":
    main()
