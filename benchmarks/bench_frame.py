"""Per-frame apply (issue 38 item 5): 1M points with normals, k = 4 (one handle) and k = 8.

Times :func:`splatdeform.deform.arrays.deform_frame` (row blocks on the usable cores, one BLAS
thread each, scratch per thread) against the previous single-threaded cache-blocked version,
kept below as ``deform_frame_reference`` for the ratio, in one run: median of ``--runs`` after
three warm-up calls, under one BLAS thread as the editor runs it (``editor/frames.py``). Also
checks the positions are bit-identical (same product and sum) and the normals equal within
float32 rounding. Target: <= 12 ms for 1M + normals. Also times the OpenCL backend
(``kernels/frame.cl``; ``deform_frame(..., backend="opencl")``, the editor's ``auto``) on the
same arrays.

    python benchmarks/bench_frame.py [--points 1000000] [--runs 20] [--busy 2]
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from splatdeform.blas import blas_threads  # noqa: E402
from splatdeform.deform.arrays import _frame_threads, deform_frame  # noqa: E402


def deform_frame_reference(positions, normals, values, gradients, delta_c, *, chunk=4096):
    """The per-frame path before issue 38 (single thread, per-chunk temporaries)."""
    n, k = values.shape
    dt = values.dtype
    d = np.asarray(delta_c).astype(dt)
    out_p = np.empty((n, 3), dtype=dt)
    out_n = None if normals is None else np.empty((n, 3), dtype=dt)
    mix = None
    if normals is not None:
        mix = np.einsum("ka,bc->kbac", d, np.eye(3, dtype=dt)).reshape(3 * k, 9)
    for s in range(0, n, chunk):
        e = min(s + chunk, n)
        np.matmul(values[s:e], d, out=out_p[s:e])
        out_p[s:e] += positions[s:e]
        if mix is None:
            continue
        j = gradients[s:e].reshape(e - s, 3 * k) @ mix
        j[:, 0] += 1
        j[:, 4] += 1
        j[:, 8] += 1
        j00, j01, j02, j10, j11, j12, j20, j21, j22 = j.T
        nx, ny, nz = normals[s:e].T.astype(dt, copy=False)
        ox = (j11 * j22 - j12 * j21) * nx + (j12 * j20 - j10 * j22) * ny \
            + (j10 * j21 - j11 * j20) * nz
        oy = (j02 * j21 - j01 * j22) * nx + (j00 * j22 - j02 * j20) * ny \
            + (j01 * j20 - j00 * j21) * nz
        oz = (j01 * j12 - j02 * j11) * nx + (j02 * j10 - j00 * j12) * ny \
            + (j00 * j11 - j01 * j10) * nz
        inv = np.sqrt(nx * nx + ny * ny + nz * nz) / np.maximum(
            np.sqrt(ox * ox + oy * oy + oz * oz), np.finfo(dt).tiny)
        block = out_n[s:e]
        block[:, 0] = ox * inv
        block[:, 1] = oy * inv
        block[:, 2] = oz * inv
    return out_p, out_n


def case(n: int, k: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return (rng.normal(size=(n, 3)).astype(np.float32), normals.astype(np.float32),
            rng.normal(size=(n, k)).astype(np.float32),
            rng.normal(scale=0.1, size=(n, k, 3)).astype(np.float32),
            rng.normal(scale=0.3, size=(k, 3)))


def median_ms(fn, runs: int) -> float:
    for _ in range(3):
        fn()
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e3


def _spin(stop) -> None:
    while not stop.is_set():
        sum(i * i for i in range(10000))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--busy", type=int, default=0, help="CPU-busy processes beside the run")
    args = ap.parse_args()
    stop = multiprocessing.Event()
    busy = [multiprocessing.Process(target=_spin, args=(stop,)) for _ in range(args.busy)]
    for p in busy:
        p.start()
    try:
        print(f"{time.strftime('%Y-%m-%d %H:%M')}  {args.points:,} points + normals, "
              f"{_frame_threads()} threads, one BLAS thread each, busy={args.busy}, "
              f"median of {args.runs}")
        for k in (4, 8):
            a = case(args.points, k)
            with blas_threads(1):
                p_old, n_old = deform_frame_reference(*a)
                p_new, n_new = deform_frame(*a)
                t_old = median_ms(lambda a=a: deform_frame_reference(*a), args.runs)
                t_new = median_ms(lambda a=a: deform_frame(*a), args.runs)
                t_one = median_ms(lambda a=a: deform_frame(*a, threads=1), args.runs)
                p_cl, n_cl = deform_frame(*a, backend="opencl")
                t_cl = median_ms(lambda a=a: deform_frame(*a, backend="opencl"), args.runs)
            same = np.array_equal(p_old, p_new)
            diff = float(np.abs(n_old - n_new).max())
            diff_cl = max(float(np.abs(p_old - p_cl).max()), float(np.abs(n_old - n_cl).max()))
            print(f"k={k}: reference {t_old:6.1f} ms  numpy {t_new:6.1f} ms "
                  f"({t_old / t_new:.2f}x; one thread {t_one:.1f} ms)  OpenCL {t_cl:5.1f} ms "
                  f"({t_old / t_cl:.2f}x)  target <= 12 ms: "
                  f"{'met' if min(t_new, t_cl) <= 12 else 'missed'}  numpy positions "
                  f"bit-identical: {same}, normals max |diff| {diff:.1e}; OpenCL max |diff| "
                  f"{diff_cl:.1e}")
    finally:
        stop.set()
        for p in busy:
            p.join()


if __name__ == "__main__":
    main()
