"""Basis precomputation benchmark: OpenCL vs the numpy float64 reference.

    python benchmarks/bench_basis.py [--points 1000000] [--centers 200] [--big]

Workload: N points x n centers x k = 4 (a handle) with gradients. The fit is real: the incremental
fitter on a handle-like problem (fixed and handle bands of a sphere-like shell) with exactly n
centers. Flop count per point-center pair: 9 + 9k (3 sub, 3 mul + 2 add for r^2, r^3 = r^2 r;
per column 2 for the value, 1 for r w, 6 for the 3 gradient FMAs) = 45 for k = 4, plus 1 sqrt
(not counted). Peak memory is ru_maxrss of this process (of a fresh child process for --big).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from splatdeform.basis import opencl  # noqa: E402
from splatdeform.basis.reference import compute_basis as reference  # noqa: E402
from splatdeform.rbf.fit import fit_incremental  # noqa: E402


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def shell_points(n: int, seed: int) -> np.ndarray:
    """(n, 3) float64 points in a shell of radii 0.8..1 around (10, -3, 2), i.e. off-origin."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.array([10.0, -3.0, 2.0]) + d * rng.uniform(0.8, 1.0, size=(n, 1))


def handle_fit(n_centers: int, k: int = 4):
    """A fit with exactly n_centers centers: fixed band z < -0.5, handle band z > 0.5,
    rhs = affine coordinates of the handle points (rows 0 for fixed points).

    Returns (fit, frame (4, 3), bbox diagonal)."""
    cons = shell_points(max(4 * n_centers, 2000), seed=1)
    z = cons[:, 2] - 2.0
    keep = (z < -0.5) | (z > 0.5)
    cons, handle = cons[keep], z[keep] > 0.5
    h = cons[handle]
    frame = np.vstack([h.mean(axis=0), h.mean(axis=0) + np.diag(h.std(axis=0))])
    homog = np.hstack([cons, np.ones((len(cons), 1))])
    rhs = homog @ np.linalg.inv(np.hstack([frame, np.ones((4, 1))]))
    rhs[~handle] = 0.0
    fit = fit_incremental(cons, rhs[:, :k], tolerance=0.0, max_centers=n_centers)
    assert fit.n_centers == n_centers, fit.n_centers
    return fit, frame, 2.0 * np.sqrt(3.0)


def delta_frame(frame: np.ndarray) -> np.ndarray:
    a = np.deg2rad(30.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return (frame - frame[0]) @ rot.T + frame[0] + np.array([0.0, 0.0, 0.3]) - frame


def timed(fn, repeat: int = 1) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def accuracy(n_centers: int) -> tuple[float, float]:
    """Max |p' - p'_ref| / diagonal for double and Kahan-float accumulation (20k points)."""
    fit, frame, diag = handle_fit(n_centers)
    pts = shell_points(20_000, seed=3)
    d_c = delta_frame(frame)
    ref = reference(pts, fit, gradients=False).values @ d_c
    errs = []
    for precision in ("double", "float"):
        out = opencl.compute_basis(pts, fit, gradients=False, precision=precision)
        errs.append(np.abs(out.values.astype(np.float64) @ d_c - ref).max() / diag)
    return errs[0], errs[1]


def big_child(n_points: int, n_centers: int) -> None:
    """Run in a fresh process: one OpenCL basis over n_points; prints 'seconds peak_mib'."""
    fit, _, _ = handle_fit(n_centers)
    opencl.compute_basis(shell_points(1000, 5), fit)  # build + JIT outside the timing
    pts = np.empty((n_points, 3))
    for lo in range(0, n_points, 1 << 20):
        hi = min(n_points, lo + (1 << 20))
        pts[lo:hi] = shell_points(hi - lo, seed=lo)
    seconds, out = timed(lambda: opencl.compute_basis(pts, fit))
    assert np.isfinite(out.values[:: 1 << 16]).all()
    print(f"{seconds:.4f} {peak_rss_mib():.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--centers", type=int, default=200)
    parser.add_argument("--big", action="store_true", help="also time 10M points (child process)")
    parser.add_argument("--big-points", type=int, default=10_000_000)
    parser.add_argument(
        "--_big-child", dest="big_child", action="store_true", help=argparse.SUPPRESS
    )
    args = parser.parse_args()
    if args.big_child:
        big_child(args.big_points, args.centers)
        return

    n, m, k = args.points, args.centers, 4
    print(f"device: {opencl.describe_device()}")
    print("load average before (1, 5, 15 min): {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    fit, _, _ = handle_fit(m, k)
    pts = shell_points(n, seed=2)
    flops = n * m * (9 + 9 * k)

    t0 = time.perf_counter()
    opencl.compute_basis(pts[:1000], fit)  # program build (or pyopencl cache hit) + PoCL JIT
    build = time.perf_counter() - t0
    t_ocl, ocl = timed(lambda: opencl.compute_basis(pts, fit), repeat=3)
    rss_ocl = peak_rss_mib()
    t_ref, ref = timed(lambda: reference(pts, fit))
    rss_ref = peak_rss_mib()
    diff_v = np.abs(ocl.values - ref.values).max() / np.abs(ref.values).max()
    diff_g = np.abs(ocl.gradients - ref.gradients).max() / np.abs(ref.gradients).max()

    rows = [
        ("workload", f"{n:,} points x {m} centers x k={k}, gradients"),
        ("opencl build + JIT (first call)", f"{build:.3f} s"),
        ("opencl basis (best of 3)", f"{t_ocl:.3f} s"),
        ("numpy reference", f"{t_ref:.3f} s"),
        ("speed-up", f"{t_ref / t_ocl:.1f}x"),
        ("opencl GFLOP/s (45 flop/pair)", f"{flops / t_ocl / 1e9:.1f}"),
        ("numpy  GFLOP/s (same count)", f"{flops / t_ref / 1e9:.1f}"),
        ("peak RSS after opencl", f"{rss_ocl:.0f} MiB"),
        ("peak RSS after reference", f"{rss_ref:.0f} MiB"),
        ("opencl vs reference (max rel)", f"values {diff_v:.2e}, gradients {diff_g:.2e}"),
    ]
    for centers in (m, 2000):
        e_double, e_float = accuracy(centers)
        rows.append(
            (
                f"|p'-p'_ref|/diag, {centers} centers",
                f"double {e_double:.2e}, Kahan float32 {e_float:.2e}",
            )
        )
    if args.big:
        child = subprocess.run(
            [sys.executable, __file__, "--_big-child", "--big-points", str(args.big_points),
             "--centers", str(m)],
            check=True, capture_output=True, text=True,
        )  # fmt: skip
        seconds, peak = (float(x) for x in child.stdout.split()[-2:])
        rows.append((f"opencl {args.big_points:,} points", f"{seconds:.3f} s"))
        rows.append((f"peak RSS, {args.big_points:,} points", f"{peak:.0f} MiB (own process)"))

    load = os.getloadavg()[0]
    rows.append(("load average after (1 min)", f"{load:.2f} on {os.cpu_count()} CPUs"))
    width = max(len(name) for name, _ in rows)
    print("-" * (width + 40))
    for name, value in rows:
        print(f"{name:<{width}}  {value}")


if __name__ == "__main__":
    main()
