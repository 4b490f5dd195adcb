"""SOG codebooks that cover each attribute's whole range (issue 47 item 6), measured against
splat-transform 3.7.0 (``-g cpu``) on the shared tile and guitar, an SH3 scene and a generated
150k-splat scene stored in random order: the RMS error of the log scales, the colours (f_dc)
and the SH rest no larger than its, the largest log-scale error within 1.1x of its, the file
within 1.02x of its size (both write the splats in Morton order: tests/test_sog_order.py)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file
from scipy.spatial import cKDTree
from sh_scene import sh_tile

from data_tools import splat_transform
from data_tools.synth import gaussian_bar
from splatdeform.io import load, save
from splatdeform.io.kmeans import codebook_1d
from splatdeform.io.splats import LossyWriteWarning


def _errors(original, path: Path) -> dict[str, float]:
    decoded = load(path)
    _, nearest = cKDTree(decoded.positions).query(original.positions)   # it reorders splats
    g, h = original.gaussians, decoded.gaussians
    scale = h.scale_log[nearest] - g.scale_log
    out = {"scale_rms": float(np.sqrt((scale ** 2).mean())),
           "scale_max": float(np.abs(scale).max()),
           "dc_rms": float(np.sqrt(((h.sh_dc[nearest] - g.sh_dc) ** 2).mean()))}
    if g.sh_rest is not None and np.any(g.sh_rest):
        out["rest_rms"] = float(np.sqrt(((h.sh_rest[nearest] - g.sh_rest) ** 2).mean()))
    return out


ORACLE_RUNS = 3
SPREAD = 1.01   # the RMS errors: within 1 % of the reference's median (it varies ~2 % by run)


@pytest.fixture(scope="module")
def oracle():
    try:
        splat_transform.install()
    except splat_transform.OracleMissing as exc:
        pytest.fail(f"the splat-transform oracle is required: {exc}")


def _scene(name: str, tmp_path: Path) -> Path:
    if name == "sh_tile":
        return sh_tile(tmp_path / "tile_sh.ply")
    if name == "bar_150k":   # SH0 (the reference SH palette of 150k splats costs minutes)
        return save(gaussian_bar(150_000, seed=0), tmp_path / "bar.ply")  # in random order
    return shared_file(name)


@pytest.mark.parametrize("scene", ["splats/tile_3dgs_sh3.ply", "splats/guitar_3dgs_sh0.ply",
                                   "sh_tile", "bar_150k"])
def test_codebooks_at_the_reference_encoders_quality(oracle, tmp_path, scene) -> None:
    src = _scene(scene, tmp_path)
    model = load(src)
    # the reference encoder's k-means starts at random: its errors vary from run to run (the
    # SH rest RMS of sh_tile 0.00410-0.00418 over four runs, ours 0.00413 every time), so ours
    # is held to the median of three of its runs within SPREAD (its own spread is ~2 %), and
    # the size to the median of their sizes
    runs, sizes = [], []
    for i in range(ORACLE_RUNS):
        theirs = tmp_path / f"theirs{i}.sog"
        splat_transform.run("-w", "-q", "-g", "cpu", str(src), str(theirs))
        runs.append(_errors(model, theirs))
        sizes.append(theirs.stat().st_size)
    b = {key: float(np.median([r[key] for r in runs])) for key in runs[0]}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LossyWriteWarning)
        ours = save(model, tmp_path / "ours.sog")
    a = _errors(model, ours)
    for key in ("scale_rms", "dc_rms", "rest_rms"):
        if key in b:
            assert a[key] <= SPREAD * b[key], (key, a[key], b[key])
    assert a["scale_max"] <= 1.1 * b["scale_max"], (a["scale_max"], b["scale_max"])
    assert ours.stat().st_size <= 1.02 * np.median(sizes), (ours.stat().st_size, sizes)


def test_codebook_covers_the_range_and_infinities() -> None:
    rng = np.random.default_rng(4)
    values = np.concatenate([rng.normal(-5, 0.5, 200_000), rng.uniform(-12, -1, 300)])
    book = codebook_1d(values, 256)
    assert np.all(np.diff(book) >= 0) and len(book) == 256
    assert abs(book[0] - values.min()) < 0.25 and abs(book[-1] - values.max()) < 0.25
    nearest = book[np.abs(values[:, None] - book[None, :]).argmin(axis=1)]
    assert np.abs(nearest - values).max() < 0.25
    flat = codebook_1d(np.concatenate([values[:1000], [-np.inf, np.inf]]), 256)
    assert np.isfinite(flat).all()
    assert flat[0] == pytest.approx(values[:1000].min() - 20, abs=1e-3)
    assert flat[-1] == pytest.approx(values[:1000].max() + 20, abs=1e-3)
    few = codebook_1d(np.array([1.0, 2.0, 2.0, 3.0]), 256)
    assert set(np.unique(few)) == {1.0, 2.0, 3.0}
