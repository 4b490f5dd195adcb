"""Control-point pairs (``points:``, splatdeform.deform.points): terrain warp-back targets,
affine recovery, scipy's smoothing, and the one-line refusals."""

from __future__ import annotations

import numpy as np
import pytest

from data_tools.warps import drift_warp
from splatdeform.deform.deformation import basis_settings, fit_settings
from splatdeform.deform.points import Pairs, pair_errors, prepare_points
from splatdeform.errors import ConfigError
from splatdeform.model import PointModel
from tests.conftest import shared_file


def _prepare(model, src, dst, smoothing=0.0, fixed=None):
    pairs = Pairs(np.asarray(src, float), np.asarray(dst, float),
                  [f"points.pairs[{i}]" for i in range(len(src))])
    fixed = np.zeros(model.n_points, bool) if fixed is None else fixed
    d, pf = prepare_points(model, fixed, [], pairs, fit_fn=fit_settings(model),
                           basis_fn=basis_settings("numpy"), smoothing=smoothing)
    return d, pf, pairs


def _moved(model, d, pf):
    return model.positions[d.free_idx] + d.basis.values @ pf.delta()


def test_terrain_warp_back_rms_decreases_with_pairs():
    from splatdeform.io import load

    truth = load(shared_file("scans/lidar_terrain_522k.ply")).positions.astype(np.float64)
    lo, hi = truth.min(0), truth.max(0)
    warped = PointModel(positions=drift_warp(truth, lo, hi))
    rng = np.random.default_rng(7)
    rms = {}
    for count in (12, 30):
        idx = rng.choice(truth.shape[0], count, replace=False)
        d, pf, pairs = _prepare(warped, warped.positions[idx], truth[idx])
        back = _moved(warped, d, pf)
        err = np.linalg.norm(back - truth, axis=1)
        rms[count] = float(np.sqrt(np.mean(err * err)))
        s = np.linalg.norm(pairs.displacements, axis=1).max()
        res = np.linalg.norm(pair_errors(d, pairs, pf.delta()), axis=1)
        assert res.max() <= 1e-6 * s  # exact at the pairs (smoothing 0)
    print(f"terrain warp-back RMS over {truth.shape[0]:,} points: 12 pairs {rms[12]:.3f} m, "
          f"30 pairs {rms[30]:.3f} m")
    assert rms[30] < rms[12]


def test_affine_drift_from_four_pairs():
    rng = np.random.default_rng(1)
    model = PointModel(positions=rng.uniform(0, 100, (3000, 3)))
    a = np.array([[1.001, 0.002, 0.0], [-0.001, 0.999, 0.003], [0.0005, 0.0, 1.002]])
    t = np.array([0.5, -0.25, 0.125])
    src = rng.uniform(0, 100, (4, 3))
    d, pf, _ = _prepare(model, src, src @ a.T + t)
    want = model.positions @ a.T + t
    assert np.abs(_moved(model, d, pf) - want).max() <= 1e-9 * model.diagonal()


@pytest.mark.parametrize("smoothing", [0.0, 5.0, 500.0])
def test_smoothing_matches_scipy(smoothing):
    from scipy.interpolate import RBFInterpolator

    rng = np.random.default_rng(3)
    model = PointModel(positions=rng.uniform(0, 10, (2000, 3)))
    src = rng.uniform(0, 10, (40, 3))
    dst = src + rng.normal(0, 0.2, (40, 3))
    d, pf, _ = _prepare(model, src, dst, smoothing=smoothing)
    ref = RBFInterpolator(src, dst - src, kernel="cubic", degree=1, smoothing=smoothing)
    probe = rng.uniform(0, 10, (500, 3))
    ours = probe + (_basis(d, probe) @ pf.delta())
    assert np.abs(ours - (probe + ref(probe))).max() < 1e-7


def _basis(d, points):
    from splatdeform.basis import compute_basis

    return compute_basis(points, d.fit, gradients=False, backend="numpy").values


def test_refusals_name_the_row():
    model = PointModel(positions=np.random.default_rng(0).uniform(0, 1, (500, 3)))
    src = np.array([[0.1, 0.1, 0.1], [0.9, 0.1, 0.2], [0.2, 0.8, 0.3], [0.5, 0.5, 0.9]])
    dup = np.vstack([src, src[1]])
    with pytest.raises(ConfigError, match=r"points.pairs\[4\] duplicates points.pairs\[1\]"):
        _prepare(model, dup, dup + 0.01)
    tgt = dup + 0.01
    tgt[4] += 0.05
    with pytest.raises(ConfigError, match=r"points.pairs\[4\] conflicts with"):
        _prepare(model, dup, tgt)
    far = src.copy()
    far[2] = [5.0, 0.5, 0.5]
    with pytest.raises(ConfigError, match=r"points.pairs\[2\]: source .* outside"):
        _prepare(model, far, far)
    flat = src.copy()
    flat[:, 2] = 0.5
    with pytest.raises(ConfigError, match="ill-conditioned"):
        _prepare(model, flat, flat + 0.01)
    with pytest.raises(ConfigError, match="at least 4 pairs"):
        _prepare(model, src[:3], src[:3] + 0.01)


def test_pairs_file_and_cli(tmp_path):
    from splatdeform.cli import main
    from splatdeform.io import save

    rng = np.random.default_rng(5)
    save(PointModel(positions=rng.uniform(0, 10, (3000, 3))), tmp_path / "in.ply")
    rows = rng.uniform(1, 9, (8, 3))
    text = "id;X;Y;Z;e;n;h\n" + "".join(
        f"{i};{a[0] + 0.1};{a[1]};{a[2]};{a[0]};{a[1]};{a[2]}\n" for i, a in enumerate(rows))
    (tmp_path / "gcp.csv").write_text(text)
    (tmp_path / "e.yaml").write_text(
        "input: in.ply\noutput: out.ply\npoints:\n  pairs: {file: gcp.csv}\n"
        "  columns: [e, n, h, X, Y, Z]\n")
    assert main(["deform", str(tmp_path / "e.yaml"), "--residuals",
                 str(tmp_path / "r.csv"), "--quiet"]) == 0
    lines = (tmp_path / "r.csv").read_text().splitlines()
    assert len(lines) == 9 and lines[1].startswith("pair,gcp.csv line 2,")
    (tmp_path / "bad.yaml").write_text(
        "input: in.ply\noutput: out.ply\npoints:\n  pairs: {file: gcp.csv}\n")
    assert main(["deform", str(tmp_path / "bad.yaml")]) == 2


def test_select_draws_pairs_without_fitting(tmp_path, capsys):
    """``select -o`` of a points: edit: arrows of the arrow colour at every projected source and
    target (the camera file the PNG wrote); no fit (no output model)."""
    from PIL import Image

    from splatdeform.cli import main
    from splatdeform.io import save
    from splatdeform.render.camera import load_camera
    from splatdeform.render.compare import LABEL_HEIGHT
    from splatdeform.render.overlay import project
    from splatdeform.render.pairs import ARROW_COLOR, CHECK_COLOR

    rng = np.random.default_rng(4)
    save(PointModel(positions=rng.uniform(0, 10, (5000, 3))), tmp_path / "in.ply")
    src = np.array([[1, 1, 1], [9, 1, 2], [5, 9, 5], [5, 5, 9], [2, 7, 3]], float)
    dst = src + [[0.6, 0, 0], [0, 0.7, 0], [0, 0, 0.8], [0.5, 0.5, 0], [-0.6, 0, 0.3]]
    rows = ", ".join(str([*a, *b]) for a, b in zip(src.tolist(), dst.tolist(), strict=True))
    (tmp_path / "e.yaml").write_text(
        f"input: in.ply\noutput: out.ply\npoints:\n  pairs: [{rows}]\n"
        "  check_pairs: [[3, 3, 3, 3.5, 3, 3]]\n")
    out = tmp_path / "sel.png"
    assert main(["select", str(tmp_path / "e.yaml"), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "pairs 5, check pairs 1 (select fits nothing" in text
    assert "regions: none  free 5,000  of 5,000 points" in text
    assert not (tmp_path / "out.ply").exists()
    image = np.asarray(Image.open(out).convert("RGB"))
    camera, size = load_camera(tmp_path / "sel.camera.json")
    strip = image.shape[0] - size[1]   # the legend wraps: whole lines of LABEL_HEIGHT
    assert strip % LABEL_HEIGHT == 0 and strip >= LABEL_HEIGHT
    for color, points in ((ARROW_COLOR, np.vstack([src, dst])),
                          (CHECK_COLOR, np.array([[3.0, 3, 3], [3.5, 3, 3]]))):
        hit = np.all(image == color, axis=2)
        xy, front = project(camera, points, size)
        assert front.all()
        for x, y in xy:
            r, c = int(round(y)) + strip, int(round(x))
            assert hit[max(r - 6, 0):r + 7, max(c - 6, 0):c + 7].any(), (color, x, y)
    # a refusal names the row, as deform's
    (tmp_path / "bad.yaml").write_text(
        "input: in.ply\noutput: out.ply\npoints:\n  pairs: [[1,1,1,2,1,1],[1,1,1,2,1,1],"
        "[9,1,2,9,1,2],[5,9,5,5,9,5],[5,5,9,5,5,9]]\n")
    assert main(["select", str(tmp_path / "bad.yaml"), "-o", str(tmp_path / "b.png")]) == 2
    assert "points.pairs[1] duplicates points.pairs[0]" in capsys.readouterr().err


def test_arrow_exaggeration_is_round():
    from splatdeform.render.pairs import exaggeration

    assert exaggeration(np.array([[1.0, 0, 0]]), 10.0) == 1.0
    assert exaggeration(np.array([[0.01, 0, 0]]), 100.0) == 500.0
