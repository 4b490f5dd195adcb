"""A seeded synthetic airborne LiDAR scan, written as LAS/LAZ in chunks (any size, bounded
memory): rolling terrain (class 2), box buildings with flat roofs (class 6) and round tree
crowns (class 5), with intensity, return numbers and GPS time; no RGB (point format 1), so
renders colour it by elevation.

Run ``python -m data_tools.lidar OUT.las --points 25000000`` for the big-render benchmark.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

EXTENT = 1000.0   # metres, square
BUILDINGS = 40
TREES = 300


def _terrain(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 20 * np.sin(x / 170.0) * np.cos(y / 230.0) + 0.01 * x


def _layout(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(buildings (B, 5): x0 y0 x1 y1 height, trees (T, 4): x y radius height)."""
    rng = np.random.default_rng(seed)
    lo = rng.uniform(50, EXTENT - 100, (BUILDINGS, 2))
    size = rng.uniform(15, 45, (BUILDINGS, 2))
    heights = rng.uniform(6, 30, (BUILDINGS, 1))
    buildings = np.hstack([lo, lo + size, heights])
    trees = np.column_stack([rng.uniform(0, EXTENT, (TREES, 2)), rng.uniform(2, 6, TREES),
                             rng.uniform(5, 15, TREES)])
    return buildings, trees


def lidar_chunk(n: int, rng: np.random.Generator, buildings: np.ndarray,
                trees: np.ndarray) -> dict[str, np.ndarray]:
    """n points scattered uniformly over the area: x, y, z (n,) float64, classification,
    intensity, return_number, gps_time."""
    x = rng.uniform(0, EXTENT, n)
    y = rng.uniform(0, EXTENT, n)
    ground = _terrain(x, y)
    z = ground + rng.normal(0, 0.03, n)
    cls = np.full(n, 2, dtype=np.uint8)
    for x0, y0, x1, y1, h in buildings:
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        z[inside] = _terrain(np.array([x0]), np.array([y0]))[0] + h
        cls[inside] = 6
    tx, ty, tr, th = (trees[:, i] for i in range(4))
    for i in range(trees.shape[0]):
        d2 = (x - tx[i]) ** 2 + (y - ty[i]) ** 2
        inside = (d2 <= tr[i] ** 2) & (cls == 2)
        crown = np.sqrt(np.maximum(tr[i] ** 2 - d2[inside], 0.0))
        z[inside] = ground[inside] + th[i] + crown * rng.uniform(0.5, 1.0, crown.size)
        cls[inside] = 5
    intensity = np.where(cls == 2, 300, np.where(cls == 6, 900, 150)) + rng.integers(0, 100, n)
    returns = np.where(cls == 5, rng.integers(1, 3, n), 1).astype(np.uint8)
    return {"x": x, "y": y, "z": z, "classification": cls,
            "intensity": intensity.astype(np.uint16), "return_number": returns,
            "gps_time": np.sort(rng.uniform(0, 3600, n))}


def write_lidar(path: str | Path, n_points: int, *, seed: int = 0,
                chunk: int = 2_000_000) -> Path:
    """Write ``n_points`` as LAS 1.2 point format 1 (LAZ for a .laz path) in chunks."""
    import laspy

    path = Path(path)
    buildings, trees = _layout(seed)
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([500000.0, 5400000.0, 0.0])
    rng = np.random.default_rng(seed + 1)
    with laspy.open(path, mode="w", header=header) as writer:
        for start in range(0, n_points, chunk):
            m = min(chunk, n_points - start)
            data = lidar_chunk(m, rng, buildings, trees)
            rec = laspy.ScaleAwarePointRecord.zeros(m, header=header)
            rec.x = data["x"] + 500000.0
            rec.y = data["y"] + 5400000.0
            rec.z = data["z"] + 100.0
            for name in ("classification", "intensity", "return_number", "gps_time"):
                rec[name] = data[name]
            rec.number_of_returns = np.maximum(data["return_number"], 1)
            writer.write_points(rec)
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("out", type=Path, help="output .las or .laz")
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    write_lidar(args.out, args.points, seed=args.seed)
    print(f"wrote {args.out} ({args.points:,} points)")


if __name__ == "__main__":
    main()
