"""Seeded stand-ins for three real scans the fit benchmark must win on, built from the shared
test data (``../shared/data``, never copied into the repository).

``benchmarks/fit_table.py`` times the default fit against scipy's dense solve on them:

- :func:`sh3_tile_14k`: the SH3 3DGS tile (6,831 splats) densified to ~14k splats: every splat
  and one seeded copy jittered by half its splat scale (a capture twice as dense, with the
  same thick, noisy splat shells);
- :func:`mesh_134k`: the 134,345-vertex Igea scan as a plain triangle mesh (its rings are one
  vertex wide); its edit's handle starts at 75% of the longest axis (m = 2,754);
- :func:`head_surfels_45k`: the 45k-surfel head scan as it is (its edit takes wider rings,
  ``neighbors`` in :data:`STANDINS`, to land near the real scan's ring count).

Run ``python -m data_tools.standins`` to print their sizes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splatdeform.io import load
from splatdeform.model import PointModel

#: The shared test data next to the project checkout.
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def available() -> bool:
    """Whether the shared files the stand-ins are made from are there."""
    return all((SHARED / p).is_file() for p in ("splats/tile_3dgs_sh3.ply", "scans/bunny.ply",
                                               "scans/head_surfels.ply"))


def sh3_tile_14k(seed: int = 5) -> PointModel:
    """~13.7k splat centers (N, 3): the SH3 tile's 6,831 and a copy of each moved by a normal
    draw of half its splat's largest scale per axis (seeded). Positions only: the fit sees
    nothing else."""
    tile = load(SHARED / "splats" / "tile_3dgs_sh3.ply")
    pos = tile.positions
    rng = np.random.default_rng(seed)
    if tile.gaussians is not None:
        size = np.exp(np.asarray(tile.gaussians.scale_log, dtype=np.float64)).max(axis=1)
    else:  # pragma: no cover - the shared tile has its scales
        size = np.full(pos.shape[0], 1e-3 * float(np.linalg.norm(np.ptp(pos, axis=0))))
    copy = pos + 0.5 * size[:, None] * rng.standard_normal(pos.shape)
    return PointModel(positions=np.concatenate([pos, copy]))


def mesh_134k() -> PointModel:
    """The Igea scan mesh as a plain triangle mesh: 134,345 vertices (N, 3) and its 268,686
    triangles (F, 3) as the loader triangulates its strips (no ``tristrips`` element left: a
    plain ``face`` PLY would load to this model)."""
    igea = load(SHARED / "edge_cases" / "igea_tristrips.ply")
    return PointModel(positions=igea.positions, faces=np.asarray(igea.faces, dtype=np.int64),
                      kind="mesh")


def head_surfels_45k() -> PointModel:
    """The head scan's 45,428 surfels (positions, normals, radii as loaded)."""
    return load(SHARED / "scans" / "head_surfels.ply")


#: name -> (maker, ``boundary.neighbors``, fixed end, handle start): the edit of
#: ``fit_table.py`` (fixed: the longest axis up to ``fixed end``, handle: from ``handle start``,
#: fractions of the bounding box), chosen to land near the real scans' ring counts
#: (2,196 / 2,754 / 728; here 2,187 / 2,754 / 724).
STANDINS = {
    "standin SH3 tile 14k": (sh3_tile_14k, 12, 0.3, 0.8),
    "standin mesh 134k": (mesh_134k, 10, 0.3, 0.75),
    "standin head surfels 45k": (head_surfels_45k, 22, 0.3, 0.8),
}


if __name__ == "__main__":
    for name, (make, neighbors, _, _) in STANDINS.items():
        model = make()
        print(f"{name}: {model.n_points:,} points, {model.n_faces:,} faces, "
              f"neighbors {neighbors}")
