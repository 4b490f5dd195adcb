"""Seeded synthetic scans for tests and the demo: a bumpy bar and a sphere.

Both are oriented point clouds with surfel radii (the mean spacing), optionally written as PLY.
The generators live in the package (:mod:`splatdeform.examples.scans`, which
``splatdeform example`` writes from an installed wheel); this module re-exports them and adds
the benchmarks' Gaussian bar. Run ``python -m data_tools.synth OUT_DIR`` to write the demo scans.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from splatdeform.examples.scans import bumpy_bar, sphere
from splatdeform.model import PointModel

__all__ = ["bumpy_bar", "gaussian_bar", "sphere"]


def gaussian_bar(n_points: int = 150000, *, sh_degree: int = 0, seed: int = 0) -> PointModel:
    """A 3DGS model of n Gaussians on the bumpy bar (benchmarks at real-scene sizes): random
    rotations, 2-10 mm scales, logit opacities, SH DC colours and ``sh_degree`` bands."""
    from splatdeform.model import Gaussians

    rng = np.random.default_rng(seed)
    bar = bumpy_bar(n_points, seed=seed)
    q = rng.normal(size=(n_points, 4)).astype(np.float32)
    rest = None
    if sh_degree:
        rest = rng.normal(scale=0.1, size=(n_points, 3 * ((sh_degree + 1) ** 2 - 1)))
    g = Gaussians(scale_log=np.log(rng.uniform(0.002, 0.01, (n_points, 3))).astype(np.float32),
                  rotation=q / np.linalg.norm(q, axis=1, keepdims=True),
                  opacity=rng.normal(size=n_points).astype(np.float32),
                  sh_dc=rng.normal(size=(n_points, 3)).astype(np.float32),
                  sh_rest=None if rest is None else rest.astype(np.float32))
    return PointModel(positions=bar.positions, gaussians=g, kind="gaussians")


def main(argv: list[str] | None = None) -> None:
    from splatdeform.io import save

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--points", type=int, default=20000)
    args = parser.parse_args(argv)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    save(bumpy_bar(args.points), args.out_dir / "bar.ply")
    save(sphere(args.points // 2), args.out_dir / "sphere.ply")
    print(f"wrote {args.out_dir / 'bar.ply'} and {args.out_dir / 'sphere.ply'}")


if __name__ == "__main__":
    main()
