"""``splatdeform deform`` end to end at the paper's scale against scipy (issue 38's case).

A generated 270k-point bumpy bar; the fit table's typical handle edit (fixed: the first 30 % of
the longest axis, handle: the last 20 %, turned 30 degrees about an axis across it at its
centroid and moved 10 % of the diagonal), C2 rings with the default 10 neighbours. Ours: the
whole ``splatdeform deform EDIT.yaml`` process, interpreter, imports and OpenCL start-up
included, from start to the written file (best of 3 after a warm-up run; byte-compiled, as an
installed package runs). scipy: ``RBFInterpolator(kernel="cubic", degree=1)`` fitted through
every ring point, then evaluated at every free point, in this process (best of 2): the
comparison favours scipy (no start-up, no load, no save). Idle, then beside ``--busy`` CPU-bound
processes, ratios taken within each.

    python benchmarks/bench_e2e.py [--points 270000] [--busy 2]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from fit_table import constraints_of  # noqa: E402

from data_tools.synth import bumpy_bar  # noqa: E402
from splatdeform.deform.handle import compose_transform, delta_for_transform  # noqa: E402
from splatdeform.edit.selectors import Box, select  # noqa: E402
from splatdeform.io import save  # noqa: E402

FIXED_END, HANDLE_START, DEGREES, MOVE, NEIGHBORS = 0.3, 0.8, 30.0, 0.1, 10


def _spin(stop) -> None:
    while not stop.is_set():
        pass


def edit_yaml(model, folder: Path) -> Path:
    """The edit as the user writes it; the bar's longest axis is x, 'across' is y."""
    lo, hi = model.bbox()
    assert int(np.argmax(hi - lo)) == 0
    move = MOVE * model.diagonal()
    path = folder / "bar.yaml"
    path.write_text(
        "input: bar.ply\noutput: bar_bent.ply\nregions:\n  units: relative\n"
        f"  fixed: [{{box: {{min: [0, 0, 0], max: [{FIXED_END}, 1, 1]}}}}]\n"
        f"  handle: [{{box: {{min: [{HANDLE_START}, 0, 0], max: [1, 1, 1]}}}}]\n"
        f"handle:\n  transform: {{pivot: centroid, rotate: {{axis: [0, 1, 0], degrees: {DEGREES}}},"
        f" translate: [0, 0, {move!r}]}}\n"
        f"boundary: {{continuity: 2, neighbors: {NEIGHBORS}}}\n")
    return path


def scipy_side(model) -> tuple[float, float, int, int]:
    """(fit s, evaluate s, ring points m, free points) of scipy on the same edit."""
    from scipy.interpolate import RBFInterpolator

    fixed = select(model, [Box((0, 0, 0), (FIXED_END, 1, 1))], "relative")
    handle = select(model, [Box((HANDLE_START, 0, 0), (1, 1, 1))], "relative")
    d = constraints_of(model, fixed, handle, NEIGHBORS)  # the fit table's: rings, no fit
    matrix = compose_transform(pivot=model.positions[handle].mean(0), axis=(0, 1, 0),
                               degrees=DEGREES, translate=(0, 0, MOVE * model.diagonal()))
    disp = d.constraint_rhs @ delta_for_transform(d.control_points, matrix)
    free = model.positions[d.free_idx]
    t_fit = t_eval = np.inf
    for _ in range(2):
        t0 = time.perf_counter()
        rbf = RBFInterpolator(d.constraint_points, disp, kernel="cubic", degree=1)
        t1 = time.perf_counter()
        rbf(free)
        t2 = time.perf_counter()
        t_fit, t_eval = min(t_fit, t1 - t0), min(t_eval, t2 - t1)
    return t_fit, t_eval, d.constraint_idx.size, d.free_idx.size


def ours(edit: Path) -> tuple[float, str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = str(ROOT)
    cmd = [sys.executable, "-m", "splatdeform.cli", "deform", str(edit)]
    subprocess.run(cmd, check=True, capture_output=True, env=env, cwd=edit.parent)  # warm
    best, stages = np.inf, ""
    for _ in range(3):
        t0 = time.perf_counter()
        out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env,
                             cwd=edit.parent).stdout
        wall = time.perf_counter() - t0
        if wall < best:
            best = wall
            stages = "  ".join(f"{line.split()[0]} {float(line.split()[1]):.3f}"
                               for line in out.splitlines()
                               if len(line.split()) == 3 and line.split()[2] == "s")
    return best, stages


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=270_000)
    ap.add_argument("--busy", type=int, default=2, help="CPU-bound processes in the second run")
    args = ap.parse_args()
    model = bumpy_bar(args.points, seed=7)
    print(f"{time.strftime('%Y-%m-%d %H:%M')} on {platform.node()} ({os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}); {model.n_points:,} points")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        save(model, folder / "bar.ply")
        edit = edit_yaml(model, folder)
        for busy in (0, args.busy):
            stop = multiprocessing.Event()
            procs = [multiprocessing.Process(target=_spin, args=(stop,)) for _ in range(busy)]
            for p in procs:
                p.start()
            try:
                t_fit, t_eval, m, n_free = scipy_side(model)
                wall, stages = ours(edit)
            finally:
                stop.set()
                for p in procs:
                    p.join()
            print(f"beside {busy} busy: {m:,} ring points, {n_free:,} free points; scipy fit "
                  f"{t_fit:.2f} s + evaluate {t_eval:.2f} s = {t_fit + t_eval:.2f} s; "
                  f"splatdeform deform {wall:.2f} s (stages: {stages}); ratio "
                  f"{(t_fit + t_eval) / wall:.2f}x")


if __name__ == "__main__":
    main()
