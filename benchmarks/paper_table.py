"""The paper's results table (Botsch & Kobbelt 2005, Table 1) re-measured in one run.

A generated 270k-point bumpy bar, a handle edit with C2 rings (about 4.1k constraints), then:
dense solve on all constraints (scipy RBFInterpolator, cubic + linear, i.e. an LU of the full
system), our incremental QR (centers, time), basis precomputation (numpy reference and OpenCL)
for the free points, and the per-frame CPU apply (positions + normals of the free points, float32).
The paper's 2005 figures are printed beside ours.

    python benchmarks/paper_table.py [--points 270000] [--tolerance 1e-4]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data_tools.synth import bumpy_bar  # noqa: E402
from splatdeform import deform as df  # noqa: E402
from splatdeform.basis import compute_basis  # noqa: E402
from splatdeform.basis.opencl import describe_device  # noqa: E402
from splatdeform.frame import deform_frame  # noqa: E402
from splatdeform.handle import compose_transform, delta_for_transform  # noqa: E402
from splatdeform.rbf import Normalization, fit_incremental  # noqa: E402
from splatdeform.regions import Box, select  # noqa: E402

PAPER = {"dense": 153.0, "qr": 1.99, "centers": 160, "basis": 7.5, "frame_cpu": 0.27}


def timed(fn, repeats: int = 1):
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--points", type=int, default=270_000)
    ap.add_argument("--tolerance", type=float, default=1e-4)
    ap.add_argument("--neighbors", type=int, default=8)
    args = ap.parse_args()

    model = bumpy_bar(args.points, seed=7)
    fixed = select(model, [Box((0, 0, 0), (0.3, 1, 1))], "relative")
    handle = select(model, [Box((0.7, 0, 0), (1, 1, 1))], "relative")
    norm = Normalization.of(model.positions)
    fit_fn = partial(fit_incremental, tolerance=args.tolerance, max_centers=4000,
                     normalization=norm)
    t_prep, d = timed(lambda: df.prepare_handle(
        model, fixed, handle, fit_fn=fit_fn,
        basis_fn=partial(compute_basis, backend="opencl"), neighbors=args.neighbors))
    matrix = compose_transform(pivot=model.positions[handle].mean(0), axis=(0, 0, 1),
                               degrees=30, translate=(0, 0.4, 0))
    delta = delta_for_transform(d.control_points, matrix)
    m = d.constraint_idx.size
    free = model.positions[d.free_idx]

    # dense solve through all constraints: scipy's RBFInterpolator (LU of the (m+4)^2 system)
    from scipy.interpolate import RBFInterpolator

    disp = d.constraint_rhs @ delta
    t_dense, rbf = timed(lambda: RBFInterpolator(d.constraint_points, disp, kernel="cubic",
                                                 degree=1))
    t_dense_eval, dense_free = timed(lambda: rbf(free))

    t_qr, fit = timed(lambda: fit_fn(d.constraint_points, d.constraint_rhs), 3)
    t_np, basis_np = timed(lambda: compute_basis(free, fit, backend="numpy"))
    compute_basis(free[:1000], fit, backend="opencl")  # build the program once
    t_cl, basis_cl = timed(lambda: compute_basis(free, fit, backend="opencl"), 3)

    pos32 = free.astype(np.float32)
    nrm32 = model.normals[d.free_idx].astype(np.float32)
    t_frame, (p_new, _) = timed(lambda: deform_frame(
        pos32, nrm32, basis_cl.values, basis_cl.gradients, delta.astype(np.float32)), 5)
    ours_free = p_new.astype(np.float64) - free
    diag = model.diagonal()
    diff = np.abs(ours_free - dense_free).max() / np.abs(dense_free).max()
    cl_err = np.abs((basis_cl.values - basis_np.values) @ delta).max() / diag

    print(f"paper table re-measured {time.strftime('%Y-%m-%d')} on {platform.node()} "
          f"({os.cpu_count()} cores, {platform.processor() or platform.machine()}); "
          f"OpenCL device: {describe_device()}")
    print(f"model: generated bumpy bar, {model.n_points:,} points; {m:,} constraints "
          f"(C2 rings, kNN {args.neighbors}); {d.free_idx.size:,} free points; "
          f"tolerance {args.tolerance:g}")
    rows = [
        ("dense solve, all constraints (scipy LU)", f"{t_dense:.2f} s", f"{PAPER['dense']} s"),
        ("  scipy evaluate on the free points", f"{t_dense_eval:.2f} s", "-"),
        ("incremental QR fit", f"{t_qr:.3f} s, {fit.n_centers} centers",
         f"{PAPER['qr']} s, {PAPER['centers']} RBFs"),
        ("basis precomputation, numpy float64", f"{t_np:.2f} s", f"{PAPER['basis']} s"),
        ("basis precomputation, OpenCL", f"{t_cl:.3f} s", "-"),
        ("per frame, CPU (positions + normals)", f"{t_frame * 1e3:.1f} ms",
         f"{PAPER['frame_cpu'] * 1e3:.0f} ms"),
    ]
    print(f"{'step':<42}{'ours':>26}{'paper (2005)':>24}")
    for name, ours, paper in rows:
        print(f"{name:<42}{ours:>26}{paper:>24}")
    print("tolerance sweep (fit on the handle's M; error = largest constraint error for the "
          "applied transform, / diagonal):")
    for tol in (1e-2, 1e-3, 1e-4):
        sweep_fn = partial(fit_incremental, tolerance=tol, max_centers=4000, normalization=norm)
        t_s, f_s = timed(lambda fn=sweep_fn: fn(d.constraint_points, d.constraint_rhs), 3)
        b_s = compute_basis(d.constraint_points, f_s, gradients=False, backend="numpy")
        err = np.linalg.norm((b_s.values - d.constraint_rhs) @ delta, axis=1).max() / diag
        print(f"  tol {tol:g}: {f_s.n_centers:5d} centers, {t_s:.3f} s "
              f"({t_dense / t_s:.1f}x scipy's dense fit), max constraint error {err:.1e}")
    print(f"ratios: dense fit / our fit {t_dense / t_qr:.2f}x; numpy basis / OpenCL basis "
          f"{t_np / t_cl:.1f}x; (scipy fit + evaluate) / (our fit + OpenCL basis) "
          f"{(t_dense + t_dense_eval) / (t_qr + t_cl):.1f}x")
    print(f"accuracy: free-point displacement vs dense solve {diff:.2%} of the largest; "
          f"OpenCL vs numpy basis {cl_err:.1e} of the diagonal; fit residual "
          f"{fit.residuals[-1].max():.2e}")
    print(f"whole precompute (rings + fit + OpenCL basis) {t_prep:.2f} s; peak memory "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
