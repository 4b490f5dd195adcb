"""The cost of splitting surfel discs (``gaussians.split: auto`` on a model with tangent axes,
issue 46 item 3): in-memory apply time split against unsplit on a generated bar of 150,000
elliptic discs (tangent semi-axes 0.024-0.06, the extent of ``bench_needles.surface_scene``'s
splats at +-2 sigma) bent 60 degrees, and the discs split / children written.

    python benchmarks/bench_surfel_split.py [--surfels 150000] [--degrees 60] [--repeats 3]

Prints one JSON line per mode (best apply time of ``--repeats``, split counts) and the ratio.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_needles import edit_config  # noqa: E402

from data_tools.synth import bumpy_bar  # noqa: E402
from splatdeform import deform as df  # noqa: E402
from splatdeform.edit import plain  # noqa: E402
from splatdeform.edit.config import parse_edit  # noqa: E402
from splatdeform.edit.run import precompute  # noqa: E402
from splatdeform.model import PointModel  # noqa: E402


def surfel_scene(n: int = 150_000, seed: int = 4) -> PointModel:
    """The bumpy bar (4 x 1 x 1) as ``n`` elliptic discs: u, v tangent, a random turn about
    the normal, semi-axes uniform in [0.024, 0.06]."""
    rng = np.random.default_rng(seed)
    bar = bumpy_bar(n, seed=seed)
    nrm = bar.normals
    helper = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(nrm, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(nrm, t1)
    ang = rng.uniform(0, np.pi, n)[:, None]
    u, v = np.cos(ang) * t1 + np.sin(ang) * t2, -np.sin(ang) * t1 + np.cos(ang) * t2
    axes = np.stack([u * rng.uniform(0.024, 0.06, (n, 1)), v * rng.uniform(0.024, 0.06, (n, 1))],
                    axis=1)
    return PointModel(positions=bar.positions, normals=nrm, colors=bar.colors, axes=axes,
                      kind="surfel_axes")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surfels", type=int, default=150_000)
    ap.add_argument("--degrees", type=float, default=60.0)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    model = surfel_scene(args.surfels)
    cfg = parse_edit(edit_config(model, args.degrees, 0.0), "bench")
    deformation = precompute(cfg, model, Path("."))
    delta_c, matrix = plain.control_displacement(cfg, model, deformation)
    best = {}
    for mode in ("off", "auto"):
        times, stats = [], {}
        for _ in range(args.repeats):
            stats = {}
            t0 = time.perf_counter()
            out = df.apply(deformation, model, delta_c, moving_matrix=matrix, stats=stats,
                           split=mode)
            times.append(time.perf_counter() - t0)
        best[mode] = min(times)
        print(json.dumps({"mode": mode, "apply_s": round(best[mode], 3),
                          "points": out.n_points,
                          "split_surfels": stats.get("split_splats", 0),
                          "children": stats.get("split_children", 0),
                          "capped": stats.get("split_capped", 0)}), flush=True)
    print(json.dumps({"ratio": round(best["auto"] / best["off"], 2)}))


if __name__ == "__main__":
    main()
