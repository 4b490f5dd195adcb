"""The measured table behind the default ``fit.tolerance`` and ``fit.max_centers``.

For every PLY scan and splat file in ``../shared/data`` and the generated benchmark scenes, a
typical handle edit (fixed: the first 30% of the bounding box along its longest axis; handle: the
last 20%; the handle rotated 30 degrees about an axis across the model and moved 10% of the
diagonal), with C2 rings, at several tolerances:

- centers, fit time, max and RMS constraint error |r| (dimensionless, in the coordinates of M);
- the free-region deviation from the exact interpolant (scipy ``RBFInterpolator`` cubic, degree
  1, through all constraints) as a fraction of the largest displacement of any handle point —
  the one denominator used in the README, the tests and the benchmarks.

    python benchmarks/fit_table.py [--tolerances 1e-3,3e-4,1e-4] [--selection greedy]
          [--max-free 20000] [--only NAME]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data_tools.synth import bumpy_bar, sphere  # noqa: E402
from splatdeform import deform as df  # noqa: E402
from splatdeform.basis.reference import evaluate_field  # noqa: E402
from splatdeform.basis.result import Basis  # noqa: E402
from splatdeform.deform.handle import compose_transform, delta_for_transform  # noqa: E402
from splatdeform.edit.selectors import Box, select  # noqa: E402
from splatdeform.io import load  # noqa: E402
from splatdeform.model import PointModel  # noqa: E402
from splatdeform.rbf import Normalization, fit_incremental  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def shared_files() -> list[Path]:
    if not SHARED.is_dir():
        return []
    return sorted(p for sub in ("scans", "splats", "edge_cases")
                  for p in (SHARED / sub).glob("*.ply"))


def typical_edit(model: PointModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """fixed, handle masks (N,) and the 4x4 handle transform of the typical edit."""
    lo, hi = model.bbox()
    axis = int(np.argmax(hi - lo))
    box_min, box_max = np.zeros(3), np.ones(3)
    f_max, h_min = box_max.copy(), box_min.copy()
    f_max[axis], h_min[axis] = 0.3, 0.8
    fixed = select(model, [Box(tuple(box_min), tuple(f_max))], "relative")
    handle = select(model, [Box(tuple(h_min), tuple(box_max))], "relative")
    across = np.zeros(3)
    across[(axis + 1) % 3] = 1.0
    move = np.zeros(3)
    move[(axis + 2) % 3] = 0.1 * model.diagonal()
    matrix = compose_transform(pivot=model.positions[handle].mean(0), axis=across, degrees=30.0,
                               translate=move)
    return fixed, handle, matrix


def constraints_of(model: PointModel, fixed: np.ndarray, handle: np.ndarray,
                   neighbors: int = 10) -> df.Deformation:
    """Rings and M of the edit (no basis: the fit and deviation are measured separately)."""
    def no_basis(points: np.ndarray, fit) -> Basis:
        return Basis(np.zeros((points.shape[0], fit.k)), None)

    def trivial_fit(points: np.ndarray, rhs: np.ndarray):
        return fit_incremental(points, rhs, tolerance=1.0, max_centers=0)

    return df.prepare_handle(model, fixed, handle, fit_fn=trivial_fit, basis_fn=no_basis,
                             neighbors=neighbors)


def scenes(only: str | None):
    gen = {
        "generated bumpy bar 270k": lambda: bumpy_bar(270_000, seed=7),
        "generated sphere 100k": lambda: sphere(100_000, seed=3),
    }
    for name, make in gen.items():
        if only is None or only in name:
            yield name, make
    for path in shared_files():
        if only is None or only in path.name:
            yield path.name, (lambda p=path: load(p))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--tolerances", default="1e-3,3e-4,1.5e-4")
    ap.add_argument("--selection", default="greedy", choices=("greedy", "fps"))
    ap.add_argument("--max-centers", type=int, default=2000)
    ap.add_argument("--max-free", type=int, default=20_000,
                    help="free points sampled (seeded) for the deviation")
    ap.add_argument("--only", help="substring of a scene name")
    args = ap.parse_args()
    tolerances = [float(t) for t in args.tolerances.split(",")]

    print(f"fit table {time.strftime('%Y-%m-%d')} on {platform.node()} ({os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}); selection {args.selection}; deviation = max "
          "free-point distance to the exact interpolant / largest handle-point displacement")
    print(f"{'scene':<32}{'points':>9}{'m':>7}{'tol':>8}{'centers':>8}{'fit s':>8}"
          f"{'max|r|':>10}{'rms|r|':>10}{'deviation':>10}{'conv':>6}{'scipy s':>9}")
    rng = np.random.default_rng(0)
    for name, make in scenes(args.only):
        model = make()
        fixed, handle, matrix = typical_edit(model)
        try:
            d = constraints_of(model, fixed, handle)
        except Exception as exc:  # a scene whose typical edit is not valid: say so, go on
            print(f"{name:<32} skipped: {exc}")
            continue
        delta = delta_for_transform(d.control_points, matrix)
        moved = model.positions[handle] @ matrix[:3, :3].T + matrix[:3, 3]
        largest = float(np.linalg.norm(moved - model.positions[handle], axis=1).max())
        free_idx = d.free_idx
        if free_idx.size > args.max_free:
            free_idx = np.sort(rng.choice(free_idx, args.max_free, replace=False))
        free = model.positions[free_idx]
        pts, rhs = d.constraint_points, d.constraint_rhs
        row(name, model.n_points, pts, rhs, delta, free, largest,
            Normalization.of(model.positions), tolerances, args)
    if args.only is None or args.only in "thin bands":
        sc = thin_band_scene()
        row("generated thin bands (bench_fit)", int(sc["n_points"]), sc["constraints"], sc["M"],
            sc["delta_c"], sc["free"], float(np.linalg.norm(sc["disp"], axis=1).max()), None,
            tolerances, args)


def thin_band_scene() -> dict[str, np.ndarray]:
    """bench_fit.py's scene: 4,136 constraints in two thin bands of a 270k-point bar."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_fit import make_scene

    return make_scene()


def row(name: str, n_points: int, pts: np.ndarray, rhs: np.ndarray, delta: np.ndarray,
        free: np.ndarray, largest: float, norm: Normalization | None, tolerances: list[float],
        args: argparse.Namespace) -> None:
    """Print one scene's lines: our fit at each tolerance against the exact interpolant."""
    from scipy.interpolate import RBFInterpolator

    # scans repeat points (LiDAR returns): the exact interpolant needs distinct constraints
    _, first = np.unique(pts, axis=0, return_index=True)
    first = np.sort(first)
    t0 = time.perf_counter()
    exact = RBFInterpolator(pts[first], rhs[first] @ delta, kernel="cubic", degree=1)
    t_exact = time.perf_counter() - t0
    exact_free = exact(free)
    for tol in tolerances:
        t0 = time.perf_counter()
        fit = fit_incremental(pts, rhs, tolerance=tol, max_centers=args.max_centers,
                              normalization=norm, selection=args.selection)
        t_fit = time.perf_counter() - t0
        dev = np.linalg.norm(evaluate_field(free, fit) @ delta - exact_free, axis=1).max()
        print(f"{name[:31]:<32}{n_points:>9,}{pts.shape[0]:>7}{tol:>8.1e}"
              f"{fit.n_centers:>8}{t_fit:>8.3f}{fit.max_error:>10.2e}{fit.rms_error:>10.2e}"
              f"{dev / largest:>10.2%}{'yes' if fit.converged else 'NO':>6}{t_exact:>9.3f}",
              flush=True)

if __name__ == "__main__":
    main()
