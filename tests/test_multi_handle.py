"""Several handles (and a curve) in one edit: k = 4 per handle (+ curve columns), one fit, one
basis, one apply; properties, errors, --reuse and a real-data edit with an image."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import shared_file

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform import deform as df
from splatdeform.basis import compute_basis
from splatdeform.basis.reference import evaluate_field
from splatdeform.deform.handle import apply_affine, compose_transform
from splatdeform.edit.config import parse_edit
from splatdeform.edit.run import control_displacement, precompute, run_edit
from splatdeform.errors import ConfigError, RegionError
from splatdeform.io import save
from splatdeform.rbf import Normalization
from splatdeform.rbf.exact import fit_exact

ROOT = Path(__file__).resolve().parents[1]
NUMPY = {"backend": "numpy"}


def bar_edit(**extra) -> dict:
    """A bar along x (length 4): the middle fixed, a handle at each end."""
    cfg = {
        "input": "bar.ply", "output": "out.ply",
        "regions": {"units": "model",
                    "fixed": [{"box": {"min": [1.6, -1, -1], "max": [2.4, 1, 1]}}]},
        "handles": [
            {"region": [{"box": {"min": [-1, -1, -1], "max": [0.6, 1, 1]}}],
             "transform": {"pivot": [0.6, 0, 0], "rotate": {"axis": [0, 0, 1], "degrees": 20}}},
            {"region": [{"box": {"min": [3.4, -1, -1], "max": [5, 1, 1]}}],
             "transform": {"pivot": [3.4, 0, 0], "rotate": {"axis": [0, 1, 0], "degrees": -15},
                           "translate": [0, 0.1, 0]}},
        ],
        **NUMPY,
    }
    cfg.update(extra)
    return cfg


@pytest.fixture(scope="module")
def bar_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("multi")
    save(bumpy_bar(6000, seed=11), root / "bar.ply")
    return root


@pytest.fixture(scope="module")
def two_handles(bar_dir):
    cfg = parse_edit(bar_edit(), "edit.yaml")
    return cfg, run_edit(cfg, bar_dir, save_output=False)


def test_each_handle_gets_its_own_transform_and_fixed_is_bit_exact(two_handles):
    cfg, res = two_handles
    d = res.deformation
    assert d.k == 8 and res.delta_c.shape == (8, 3) and len(d.handle_groups()) == 2
    assert isinstance(res.matrix, list) and len(res.matrix) == 2
    src, out = res.model.positions, res.deformed.positions
    for group, matrix in zip(d.handle_groups(), res.matrix, strict=True):
        idx = d.moving_idx[group.rows]
        np.testing.assert_array_equal(out[idx], apply_affine(matrix, src[idx]))
    np.testing.assert_array_equal(out[d.fixed], src[d.fixed])
    np.testing.assert_array_equal(res.deformed.normals[d.fixed], res.model.normals[d.fixed])
    assert res.stats["converged"]


def test_free_region_is_within_the_fit_bound_of_the_exact_interpolant(two_handles):
    _, res = two_handles
    d = res.deformation
    exact = fit_exact(d.constraint_points, d.constraint_rhs,
                      normalization=d.fit.normalization)
    free = res.model.positions[d.free_idx]
    dev = np.linalg.norm((evaluate_field(free, d.fit) - evaluate_field(free, exact))
                         @ res.delta_c, axis=1).max()
    largest = max(np.linalg.norm(apply_affine(m, res.model.positions[d.moving_idx[g.rows]])
                                 - res.model.positions[d.moving_idx[g.rows]], axis=1).max()
                  for g, m in zip(d.handle_groups(), res.matrix, strict=True))
    assert dev <= 0.03 * largest


def test_two_handles_with_one_transform_equal_one_handle_of_their_union(bar_dir):
    """Affine reproduction across handles: with a shared transform the prescribed values are
    the same as for one handle made of both regions, so the exact interpolants agree."""
    shared = {"pivot": [2, 0, 0], "rotate": {"axis": [0, 0, 1], "degrees": 10},
              "translate": [0, 0.2, 0]}
    two = bar_edit(fit={"method": "exact"})
    for h in two["handles"]:
        h["transform"] = shared
    one = bar_edit(fit={"method": "exact"})
    del one["handles"]
    one["regions"]["handle"] = [two["handles"][0]["region"][0], two["handles"][1]["region"][0]]
    one["handle"] = {"transform": shared}
    a = run_edit(parse_edit(two, "two.yaml"), bar_dir, save_output=False)
    b = run_edit(parse_edit(one, "one.yaml"), bar_dir, save_output=False)
    scale = np.abs(b.deformed.positions - b.model.positions).max()
    np.testing.assert_allclose(a.deformed.positions, b.deformed.positions, rtol=0,
                               atol=1e-8 * scale)
    np.testing.assert_allclose(a.deformed.normals, b.deformed.normals, rtol=0, atol=1e-7)


def test_jacobian_matches_finite_differences_with_two_handles(two_handles):
    _, res = two_handles
    d = res.deformation
    rng = np.random.default_rng(3)
    pts = res.model.positions[rng.choice(d.free_idx, 20, replace=False)]
    basis = compute_basis(pts, d.fit, backend="numpy")
    jac = np.eye(3)[None] + np.einsum("ke,nkd->ned", res.delta_c, basis.gradients)
    h = 1e-5 * res.model.diagonal()
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        fd = (evaluate_field(pts + step, d.fit) - evaluate_field(pts - step, d.fit)) @ (
            res.delta_c) / (2 * h)
        np.testing.assert_allclose(jac[:, :, axis], np.eye(3)[:, axis] + fd, atol=1e-6)


def test_handles_combined_with_a_curve(bar_dir):
    cfg = bar_edit(curve={"control_points": [[0.9, 0, 0.52], [1.05, 0, 0.52], [1.2, 0, 0.52],
                                             [1.3, 0, 0.52]],
                          "moved_to": [[0.9, 0, 0.56], [1.05, 0, 0.58], [1.2, 0, 0.58],
                                       [1.3, 0, 0.56]],
                          "capture_radius": 0.08, "degree": 3})
    res = run_edit(parse_edit(cfg, "c.yaml"), bar_dir, save_output=False)
    d = res.deformation
    assert d.k == 12 and [g.name for g in d.groups] == ["handles[0].region",
                                                         "handles[1].region", "curve band"]
    curve = d.groups[2]
    idx = d.moving_idx[curve.rows]
    expected = res.model.positions[idx] + d.moving_coords[curve.rows] @ res.delta_c
    np.testing.assert_array_equal(res.deformed.positions[idx], expected)
    assert np.abs(res.deformed.positions[idx] - res.model.positions[idx]).max() > 0.01


@pytest.mark.parametrize(("change", "key"), [
    (lambda c: c["handles"][1].update(region=[{"box": {"min": [0.4, -1, -1],
                                                      "max": [1.0, 1, 1]}}]),
     "handles[1].region: overlaps handles[0].region"),
    (lambda c: c["handles"][1].update(region=[{"box": {"min": [2.2, -1, -1],
                                                      "max": [3.0, 1, 1]}}]),
     "handles[1].region: overlaps regions.fixed"),
    (lambda c: c["handles"].append({"region": [{"box": {"min": [3.6, -1, -1],
                                                        "max": [5, 1, 1]}}],
                                    "matrix": np.eye(4).tolist()})
     or c["handles"][1].update(region=[{"box": {"min": [3.0, -1, -1], "max": [3.6, 1, 1]}}]),
     "handles[2].region: no point of it is adjacent to the free region"),
    (lambda c: c["handles"][0].update(region=[{"box": {"min": [9, 9, 9], "max": [10, 10, 10]}}]),
     "handles[0].region: selects no point"),
])
def test_bad_handle_sets_are_one_line_region_errors(bar_dir, change, key):
    cfg = bar_edit()
    change(cfg)
    with pytest.raises(RegionError, match=key.replace("[", r"\[").replace("]", r"\]")):
        run_edit(parse_edit(cfg, "bad.yaml"), bar_dir, save_output=False)


@pytest.mark.parametrize(("change", "text"), [
    (lambda c: c.update(handle={"transform": {}}), "handles: not together with handle"),
    (lambda c: c["regions"].update(handle=[{"box": {"min": [0, 0, 0], "max": [1, 1, 1]}}]),
     "handles: not together with handle"),
    (lambda c: c.update(handles=[]), "handles"),
    (lambda c: c["handles"][0].pop("region"), "handles[0].region"),
])
def test_bad_handles_configs_name_the_key(change, text):
    cfg = bar_edit()
    change(cfg)
    with pytest.raises(ConfigError, match=text.replace("[", r"\[").replace("]", r"\]")):
        parse_edit(cfg, "bad.yaml")


def test_reuse_with_new_transforms_for_every_handle(bar_dir):
    first = bar_dir / "reuse1.yaml"
    first.write_text(yaml.safe_dump(bar_edit(output="reuse1.ply")))
    run = [sys.executable, "-m", "splatdeform.cli", "deform"]
    res = subprocess.run([*run, str(first), "--reuse-file", str(bar_dir / "multi.npz")],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert res.returncode == 0, res.stderr
    cfg = bar_edit(output="reuse2.ply")
    cfg["handles"][0]["transform"]["rotate"]["degrees"] = -10
    cfg["handles"][1]["transform"] = {"pivot": "centroid", "translate": [0, 0, 0.2]}
    second = bar_dir / "reuse2.yaml"
    second.write_text(yaml.safe_dump(cfg))
    res = subprocess.run([*run, str(second), "--reuse-file", str(bar_dir / "multi.npz")],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert res.returncode == 0 and "reused precomputed deformation" in res.stdout, res.stderr
    fresh = run_edit(parse_edit(cfg, "fresh.yaml"), bar_dir, save_output=False)
    reused = sd.load(bar_dir / "reuse2.ply")
    # free points: the same basis, summed in another process (BLAS order): rounding apart
    np.testing.assert_allclose(reused.positions, fresh.deformed.positions, rtol=0,
                               atol=1e-12 * fresh.model.diagonal())
    d = fresh.deformation
    np.testing.assert_array_equal(reused.positions[d.moving], fresh.deformed.positions[d.moving])


def test_bunny_both_ears_bent_by_different_rotations(tmp_path):
    """Real data: both ears of the bunny bent by different rotations, the head fixed; an image
    of before/after is written."""
    bunny = shared_file("scans/bunny.ply")
    cfg = {
        "input": str(bunny), "output": str(tmp_path / "ears.ply"),
        "regions": {"units": "model",
                    "fixed": [{"box": {"min": [-1, -1, -1], "max": [1, 0.125, 1]}}]},
        "handles": [
            {"region": [{"box": {"min": [-1, 0.16, -1], "max": [-0.055, 1, 1]}}],
             "transform": {"pivot": [-0.07, 0.16, -0.01],
                           "rotate": {"axis": [0, 0, 1], "degrees": 25}}},
            {"region": [{"box": {"min": [-0.04, 0.16, -1], "max": [1, 1, 1]}}],
             "transform": {"pivot": [-0.02, 0.16, 0.0],
                           "rotate": {"axis": [1, 0, 0], "degrees": -30}}},
        ],
        "render": {"output": str(tmp_path / "ears.png"), "size": [400, 200]},
        "backend": "auto",
    }
    path = tmp_path / "ears.yaml"
    path.write_text(yaml.safe_dump(cfg))
    res = subprocess.run([sys.executable, "-m", "splatdeform.cli", "deform", str(path)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "ears.png").is_file()
    src, out = sd.load(bunny), sd.load(tmp_path / "ears.ply")
    fixed = src.positions[:, 1] <= 0.125
    np.testing.assert_array_equal(out.positions[fixed], src.positions[fixed])
    left = src.positions[:, 1] >= 0.16
    ears = [left & (src.positions[:, 0] <= -0.055), left & (src.positions[:, 0] >= -0.04)]
    moves = [np.linalg.norm(out.positions[e] - src.positions[e], axis=1).max() for e in ears]
    assert all(m > 0.005 for m in moves)
    rots = [compose_transform(pivot=np.array([-0.07, 0.16, -0.01]), axis=(0, 0, 1), degrees=25),
            compose_transform(pivot=np.array([-0.02, 0.16, 0.0]), axis=(1, 0, 0), degrees=-30)]
    for e, m in zip(ears, rots, strict=True):
        np.testing.assert_allclose(out.positions[e], apply_affine(m, src.positions[e]),
                                   atol=1e-6)


def test_prepare_handles_python_api(bar_dir):
    """The Python API: two handle masks, one fit, one basis, one apply with two matrices."""
    model = sd.load(bar_dir / "bar.ply")
    x = model.positions[:, 0]
    fixed, left, right = (x > 1.6) & (x < 2.4), x < 0.6, x > 3.4
    norm = Normalization.of(model.positions)
    from functools import partial

    from splatdeform.rbf import fit_incremental

    d = df.prepare_handles(model, fixed, [left, right],
                           fit_fn=partial(fit_incremental, normalization=norm),
                           basis_fn=partial(compute_basis, backend="numpy"))
    mats = [compose_transform(pivot=np.array([0.6, 0, 0]), axis=(0, 0, 1), degrees=20),
            compose_transform(pivot=np.array([3.4, 0, 0]), translate=(0, 0.1, 0))]
    delta = np.vstack([sd.delta_for_transform(g.frame.control_points, m)
                       for g, m in zip(d.handle_groups(), mats, strict=True)])
    out = df.apply(d, model, delta, moving_matrix=mats)
    np.testing.assert_array_equal(out.positions[right], apply_affine(mats[1],
                                                                     model.positions[right]))
    with pytest.raises(sd.InputError, match="moving_matrix"):
        df.apply(d, model, delta, moving_matrix=mats[0])


def test_edit_config_layer_gives_plain_data(bar_dir):
    """precompute/control_displacement only hand model-unit arrays to the layers below."""
    cfg = parse_edit(bar_edit(), "e.yaml")
    model = sd.load(bar_dir / "bar.ply")
    d = precompute(cfg, model, bar_dir)
    delta, mats = control_displacement(cfg, model, d)
    assert delta.shape == (8, 3) and all(m.shape == (4, 4) for m in mats)


def test_frames_interpolate_every_handle(two_handles, tmp_path):
    """--frames: frame t shows delta_c * t for all handles at once (both ends move in every
    frame; the last frame is the full edit), rendered by the real shaders."""
    from PIL import Image

    from splatdeform.edit.images import render_result
    from splatdeform.render import View

    cfg, res = two_handles
    out = render_result(res, cfg, tmp_path / "multi.gif", frames=3, view=View(size=(96, 64)))
    with Image.open(out) as gif:
        frames = []
        for i in range(gif.n_frames):
            gif.seek(i)
            frames.append(np.asarray(gif.convert("RGB"), dtype=np.int16))
    assert len(frames) == 3
    background = frames[0][0, 0]
    cols = np.flatnonzero(np.any(np.stack(frames) != background, axis=(0, 1, 3)))
    third = (cols[-1] - cols[0]) // 3  # the bar's ends: the outer thirds of its columns
    left, right = slice(cols[0], cols[0] + third), slice(cols[-1] - third, cols[-1] + 1)
    for a, b in zip(frames[:-1], frames[1:], strict=True):
        assert np.abs(a[:, left] - b[:, left]).max() > 0  # one end moves in every step
        assert np.abs(a[:, right] - b[:, right]).max() > 0  # and so does the other
