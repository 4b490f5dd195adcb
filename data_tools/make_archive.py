"""Seeded generated scans for batch tests and benchmarks: a folder and a .zip of the same files.

    python -m data_tools.make_archive OUT_DIR --scans 8 --points 4000 --broken

writes OUT_DIR/scans/scan_000.ply ... (bumpy bars of varying length and radius, every fourth a
sphere) and OUT_DIR/scans.zip with the same members. ``--broken`` makes the last two scans
unusable: a truncated binary PLY (``*_truncated.ply``) and one with NaN coordinates
(``*_nan.ply``).
"""

from __future__ import annotations

import argparse
import zipfile
from pathlib import Path

import numpy as np

from data_tools.synth import bumpy_bar, sphere
from splatdeform.io import save


def make_scans(out_dir: str | Path, n_scans: int = 8, n_points: int = 4000, *,
               broken: bool = False, spheres: bool = True, seed: int = 0,
               zip_name: str | None = "scans.zip") -> tuple[list[Path], Path | None]:
    """Write ``n_scans`` scans into ``out_dir/scans`` (and a zip of them); returns the paths."""
    out_dir = Path(out_dir)
    folder = out_dir / "scans"
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paths = []
    for i in range(n_scans):
        n = int(n_points * rng.uniform(0.8, 1.2))
        if spheres and i % 4 == 3:
            model = sphere(n, radius=float(rng.uniform(0.5, 2.0)), seed=seed + i)
            name = f"sphere_{i:03d}"
        else:
            model = bumpy_bar(n, length=float(rng.uniform(3.0, 6.0)),
                              radius=float(rng.uniform(0.3, 0.7)), seed=seed + i)
            name = f"bar_{i:03d}"
        kind = None
        if broken and i == n_scans - 2:
            kind = "truncated"
        elif broken and i == n_scans - 1:
            kind = "nan"
            model.positions[rng.choice(n, 5, replace=False)] = np.nan
        path = folder / (f"{name}_{kind}.ply" if kind else f"{name}.ply")
        save(model, path)
        if kind == "truncated":
            data = path.read_bytes()
            path.write_bytes(data[: len(data) * 2 // 3])
        paths.append(path)
    archive = None
    if zip_name:
        archive = out_dir / zip_name
        with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
            for p in paths:
                zf.write(p, f"scans/{p.name}")
    return paths, archive


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--scans", type=int, default=8)
    parser.add_argument("--points", type=int, default=4000)
    parser.add_argument("--broken", action="store_true",
                        help="make the last two scans truncated / NaN")
    parser.add_argument("--no-spheres", action="store_true", help="bars only")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    paths, archive = make_scans(args.out_dir, args.scans, args.points, broken=args.broken,
                                spheres=not args.no_spheres, seed=args.seed)
    print(f"wrote {len(paths)} scans to {args.out_dir / 'scans'} and {archive}")


if __name__ == "__main__":
    main()
