"""Helpers of the splat-format cross-checks: synthetic 3DGS scenes and a comparison of two
decodes in PLY space (quaternions up to sign, opacity after the sigmoid)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splatdeform.io.ply_format import write_ply
from splatdeform.io.splats import SplatFields, fields_of, sigmoid
from splatdeform.model import PlyElementData, PlyProperty, PlySource

SH_K = {0: 0, 1: 3, 2: 8, 3: 15}


def scene_source(n: int, degree: int = 3, seed: int = 0, spread: float = 5.0) -> PlySource:
    """A random 3DGS scene as a binary PLY source (float32 properties in the INRIA order)."""
    rng = np.random.default_rng(seed)
    cols = {"x": rng.uniform(-spread, spread, n), "y": rng.uniform(-spread, spread, n),
            "z": rng.uniform(-spread, spread, n)}
    for i in range(3):
        cols[f"f_dc_{i}"] = rng.uniform(-1.5, 1.5, n)
    for i in range(3 * SH_K[degree]):
        cols[f"f_rest_{i}"] = rng.uniform(-0.5, 0.5, n)
    cols["opacity"] = rng.uniform(-4, 4, n)
    for i in range(3):
        cols[f"scale_{i}"] = rng.uniform(-6, -1, n)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    for i in range(4):
        cols[f"rot_{i}"] = q[:, i]
    data = np.empty(n, dtype=[(c, "<f4") for c in cols])
    for c, v in cols.items():
        data[c] = v
    vertex = PlyElementData("vertex", [PlyProperty(c, "f4", "float") for c in cols], data)
    return PlySource(elements=[vertex], comments=["test scene"], text=False, byte_order="<")


def write_scene(path: Path, n: int, degree: int = 3, seed: int = 0) -> Path:
    with open(path, "wb") as f:
        write_ply(scene_source(n, degree, seed), f)
    return path


def fields(model) -> SplatFields:
    return fields_of(model, model.path, "test")


def compare(a: SplatFields, b: SplatFields, *, pos: float, scale: float, rot: float,
            alpha: float, dc: float, rest: float) -> dict[str, float]:
    """Max differences of two decodes; asserts each within its tolerance. Returns them."""
    assert a.count == b.count
    qa = a.rotation / np.linalg.norm(a.rotation, axis=1, keepdims=True)
    qb = b.rotation / np.linalg.norm(b.rotation, axis=1, keepdims=True)
    diffs = {
        "pos": float(np.abs(a.positions - b.positions).max()),
        "scale": float(np.abs(a.scale_log - b.scale_log).max()),
        "rot": float((1 - np.abs((qa * qb).sum(axis=1))).max()),
        "alpha": float(np.abs(sigmoid(a.opacity) - sigmoid(b.opacity)).max()),
        "dc": float(np.abs(a.sh_dc - b.sh_dc).max()),
        "rest": float(np.abs(a.sh_rest - b.sh_rest).max()) if a.sh_rest.size else 0.0,
    }
    assert a.sh_rest.shape == b.sh_rest.shape, (a.sh_rest.shape, b.sh_rest.shape)
    limits = {"pos": pos, "scale": scale, "rot": rot, "alpha": alpha, "dc": dc, "rest": rest}
    bad = {k: (v, limits[k]) for k, v in diffs.items() if not v <= limits[k]}
    assert not bad, f"beyond tolerance (value, limit): {bad}"
    return diffs
