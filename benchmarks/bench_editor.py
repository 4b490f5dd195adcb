"""Editor latency per pose change, server side: pose received -> new buffers handed to viser.

For a generated 1M-point surfel bar (positions + normals + shading) and a 1M-Gaussian bar
(positions + covariances, packed splat buffer): fit once, then time ``EditorApp.apply_pose``
(controller.set_pose + viewer handoff) over a sweep of handle poses on a real viser server.
Targets on the 2-core development machine: <= 150 ms (points), <= 300 ms (Gaussians).

    python benchmarks/bench_editor.py [--points 1000000] [--poses 12]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_tools.synth import bumpy_bar  # noqa: E402
from splatdeform.deform.handle import compose_transform  # noqa: E402
from splatdeform.edit.selectors import Box  # noqa: E402
from splatdeform.editor import EditorController  # noqa: E402
from splatdeform.editor.server import EditorApp  # noqa: E402
from splatdeform.model import Gaussians, PointModel  # noqa: E402


def gaussian_bar(n: int, seed: int = 0) -> PointModel:
    rng = np.random.default_rng(seed)
    bar = bumpy_bar(n, seed=seed)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    g = Gaussians(scale_log=np.log(rng.uniform(0.002, 0.01, (n, 3))).astype(np.float32),
                  rotation=q / np.linalg.norm(q, axis=1, keepdims=True),
                  opacity=rng.normal(size=n).astype(np.float32),
                  sh_dc=rng.normal(size=(n, 3)).astype(np.float32))
    return PointModel(positions=bar.positions, gaussians=g, kind="gaussians")


def measure(name: str, model: PointModel, poses: int, server) -> dict[str, float]:
    ed = EditorController(model, model_path=ROOT / f"{name}.ply", base_dir=ROOT)
    ed.add_selector("fixed", Box((-1, -1, -1), (1, 1, 1)))
    ed.add_selector("handle", Box((3, -1, -1), (5, 1, 1)))
    ed.settings.fit.tolerance = 1e-3
    t0 = time.perf_counter()
    app = EditorApp(ed, server)
    t_app = time.perf_counter() - t0
    app._fit()  # what the Fit button does
    stats = ed.fit_stats
    app.apply_pose(0, np.eye(4))  # warm-up
    total, compute = [], []
    for i in range(poses):
        matrix = compose_transform(pivot=np.array([3.5, 0, 0]), axis=(0, 0, 1),
                                   degrees=3.0 * (i + 1), translate=(0, 0.02 * i, 0))
        total.append(app.apply_pose(0, matrix))
        compute.append(ed.set_pose(matrix, full=False).seconds)
    app.close()
    return {"points": model.n_points, "fit_s": stats["seconds"], "centers": stats["centers"],
            "viewer_setup_s": t_app, "median_ms": 1000 * float(np.median(total)),
            "max_ms": 1000 * float(np.max(total)),
            "set_pose_ms": 1000 * float(np.median(compute))}


def main(argv: list[str] | None = None) -> None:
    import viser

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--poses", type=int, default=12)
    args = ap.parse_args(argv)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        rows = [("points (surfels, normals shaded)", measure("bar", bumpy_bar(args.points),
                                                              args.poses, server), 150),
                ("3DGS (covariances)", measure("splats", gaussian_bar(args.points),
                                               args.poses, server), 300)]
    finally:
        server.stop()
    print("\n| model | N | centers | fit | per pose: set_pose (moving rows) "
          "| pose -> viewer (median / max) | target |\n|---|---|---|---|---|---|---|")
    for label, r, target in rows:
        print(f"| {label} | {r['points']:,} | {r['centers']} | {r['fit_s']:.2f} s | "
              f"{r['set_pose_ms']:.0f} ms | {r['median_ms']:.0f} / {r['max_ms']:.0f} ms | "
              f"<= {target} ms |")


if __name__ == "__main__":
    main()
