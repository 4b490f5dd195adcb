"""A real splat scene with view-dependent colour for the SH tests (convert, SOG quality)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import shared_file

from splatdeform.io import load, save

TILE = "splats/tile_3dgs_sh3.ply"


def sh_tile(path: Path, seed: int = 3) -> Path:
    """The shared SH3 tile (whose f_rest are all zero) with smooth, seeded view-dependent
    colour: bands 1-3 of a few sinusoids of the position plus a little noise."""
    model = load(shared_file(TILE)).copy()
    rng = np.random.default_rng(seed)
    p = model.positions.astype(np.float64)
    freq = rng.normal(size=(3, 16)) * 1.5
    feats = np.concatenate([np.sin(p @ freq), np.cos(p @ freq)], axis=1)
    band = np.tile(np.repeat([0.12, 0.06, 0.03], [3, 5, 7]), 3)
    sh = feats @ (rng.normal(size=(32, 45)) / np.sqrt(32) * band)
    sh += rng.normal(size=sh.shape) * band / 12
    model.gaussians.sh_rest[:] = sh.astype(np.float32)
    save(model, path)
    return path
