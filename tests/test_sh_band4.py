"""SH degree 4 (issue 34): kept in the files, not drawn; a render says so once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from helpers import run_cli

from data_tools.synth import gaussian_bar
from splatdeform.io import load, save
from splatdeform.model import Gaussians, PointModel


def _degree4(path: Path) -> Path:
    bar = gaussian_bar(2000, sh_degree=3, seed=9)
    g = bar.gaussians
    rng = np.random.default_rng(9)
    rest = rng.normal(scale=0.05, size=(bar.n_points, 72)).astype(np.float32)
    for c in range(3):   # channel-major: bands 1-3 as the bar has them, band 4 random
        rest[:, 24 * c: 24 * c + 15] = g.sh_rest[:, 15 * c: 15 * c + 15]
    model = PointModel(positions=bar.positions, kind="gaussians",
                       gaussians=Gaussians(g.scale_log, g.rotation, g.opacity, g.sh_dc, rest))
    save(model, path)
    return path


def test_band4_is_kept_and_a_render_says_once_it_is_not_drawn(tmp_path: Path) -> None:
    src = _degree4(tmp_path / "d4.ply")
    assert load(src).gaussians.sh_rest.shape[1] == 72
    res = run_cli("render", src, src, "-o", tmp_path / "x.png", "--size", "320x240",
                  cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    said = [ln for ln in res.stderr.splitlines() if "SH band 4" in ln]
    assert len(said) == 1 and said[0].startswith("splatdeform: warning: "), res.stderr
    assert (tmp_path / "x.png").stat().st_size > 0


def test_the_editor_page_gets_bands_0_to_3(tmp_path: Path) -> None:
    from splatdeform.editor import EditorController
    from splatdeform.editor.payload import model_arrays, sh_degree

    src = _degree4(tmp_path / "d4.ply")
    ed = EditorController.open(src)
    arrays = model_arrays(ed, None)
    rest = load(src).gaussians.sh_rest.reshape(-1, 3, 24)
    assert sh_degree(ed) == 3 and arrays["sh_rest"].shape[1] == 45
    np.testing.assert_array_equal(arrays["sh_rest"].reshape(-1, 3, 15), rest[:, :, :15])
