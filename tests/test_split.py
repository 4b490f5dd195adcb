"""Adaptive splitting of Gaussians (issue 37): the rule on analytic fields, and on a real bend
of a generated bar: fixed splats bit-identical, determinism, bounds, every writer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from data_tools.synth import gaussian_bar
from splatdeform import deform as df
from splatdeform.deform import split as sp
from splatdeform.edit import plain
from splatdeform.edit.config import parse_edit
from splatdeform.edit.run import precompute
from splatdeform.io import load, save


def _splats(n: int, sigma: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-0.2, 0.2, (n, 3))
    scale = np.log(sigma * rng.uniform(0.8, 1.2, (n, 3))).astype(np.float32)
    q = rng.normal(size=(n, 4))
    return centers, scale, (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)


def _rule(field, jacobian, centers, scale, rot) -> sp.SplitPlan:
    def f(points, gradients):
        return field(points), (jacobian(points) if gradients else None)

    sigma, r = np.exp(scale.astype(np.float64)), sp.quaternion_to_matrix(rot)
    return sp.plan(scale, rot, jacobian(centers), sp.curvature(centers, sigma, r, f))


def test_pure_bend_splits_along_the_bent_axis() -> None:
    """x curls about the z axis at radius 1: J is a rotation at y = 0 (no stretch), but the
    field bends across a long splat's x axis (second-order term 0.2 of the first)."""
    radius = 1.0

    def field(p):
        t = p[:, 0] / radius
        return np.stack([(radius + p[:, 1]) * np.sin(t), (radius + p[:, 1]) * np.cos(t) - radius,
                         p[:, 2]], axis=1)

    def jac(p):
        t, k = p[:, 0] / radius, (radius + p[:, 1]) / radius
        j = np.zeros((p.shape[0], 3, 3))
        j[:, 0, 0], j[:, 0, 1] = k * np.cos(t), np.sin(t)
        j[:, 1, 0], j[:, 1, 1] = -k * np.sin(t), np.cos(t)
        j[:, 2, 2] = 1
        return j

    centers = np.zeros((1, 3))
    scale = np.log([[0.2, 0.01, 0.01]]).astype(np.float32)
    rot = np.array([[1.0, 0, 0, 0]], np.float32)
    result = _rule(field, jac, centers, scale, rot)
    assert result.split.all() and result.counts[0, 0] > 1
    assert (result.counts[0, 1:] == 1).all()
    # a small splat on the same bend is not split
    small = _rule(field, jac, centers, np.log([[0.02, 0.01, 0.01]]).astype(np.float32), rot)
    assert not small.split.any()


def test_pure_stretch_splits_along_the_stretched_axis() -> None:
    """x -> 3x + x^2 / 200: a 3x stretch along x, nearly (not exactly) affine."""
    def field(p):
        return np.stack([3 * p[:, 0] + p[:, 0] ** 2 / 200, p[:, 1], p[:, 2]], axis=1)

    def jac(p):
        j = np.broadcast_to(np.eye(3), (p.shape[0], 3, 3)).copy()
        j[:, 0, 0] = 3 + p[:, 0] / 100
        return j

    centers = np.zeros((1, 3))
    result = _rule(field, jac, centers, np.log([[0.05] * 3]).astype(np.float32),
                   np.array([[1.0, 0, 0, 0]], np.float32))
    assert result.split.all()
    assert result.counts[0, 0] > 1 and (result.counts[0, 1:] == 1).all()


@pytest.mark.parametrize("kind", ["uniform", "anisotropic", "shear"])
def test_affine_maps_never_split(kind: str) -> None:
    rng = np.random.default_rng(5)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    a = {"uniform": 2.5 * q, "anisotropic": q @ np.diag([4.0, 1.0, 0.3]),
         "shear": np.array([[1, 3.0, 0], [0, 1, 0], [0, 0.5, 1]])}[kind]
    b = np.array([0.3, -1.0, 2.0])
    centers, scale, rot = _splats(200, 0.05)
    result = _rule(lambda p: p @ a.T + b, lambda p: np.broadcast_to(a, (p.shape[0], 3, 3)),
                   centers, scale, rot)
    assert not result.split.any()


def test_layout_matches_the_parent_moments() -> None:
    for counts in ([2, 1, 1], [8, 1, 1], [2, 2, 2], [1, 3, 2]):
        offsets, weights = sp.layout(np.array(counts))
        c = sp.shrink(np.array(counts, float))
        assert offsets.shape[0] == np.prod(counts) <= sp.MAX_CHILDREN
        assert weights.sum() == pytest.approx(1.0)
        assert np.allclose(weights @ offsets, 0)
        var = weights @ offsets ** 2 + c ** 2
        assert np.allclose(var, 1.0)


def test_child_opacity_rule() -> None:
    logit = np.array([-np.inf, -3.0, 0.0, 4.0, np.inf], np.float32)
    out = sp.child_opacity(logit, np.full(5, 0.5))
    alpha = 1 / (1 + np.exp(-logit.astype(np.float64)))
    assert out[0] == -np.inf and out[-1] == np.inf
    expect = 1 - (1 - alpha[1:4]) ** 0.5
    assert np.allclose(1 / (1 + np.exp(-out[1:4].astype(np.float64))), expect, rtol=1e-5)


def _bend(n: int = 6000, degrees: float = 90.0):
    model = gaussian_bar(n, seed=2)
    cfg = parse_edit({
        "input": "x.ply", "output": "y.ply",
        "regions": {"units": "relative",
                    "fixed": [{"box": {"min": [0, 0, 0], "max": [0.4, 1, 1]}}],
                    "handle": [{"box": {"min": [0.6, 0, 0], "max": [1, 1, 1]}}]},
        "handle": {"transform": {"pivot": [0.6, 0.5, 0.5],
                                 "rotate": {"axis": [0, 0, 1], "degrees": degrees}}},
        "boundary": {"continuity": 1, "neighbors": 10},
        "fit": {"tolerance": 2e-3, "max_centers": 600}, "backend": "numpy"}, "test")
    deformation = precompute(cfg, model, Path("."))
    delta_c, matrix = plain.control_displacement(cfg, model, deformation)
    return model, deformation, delta_c, matrix


@pytest.fixture(scope="module")
def bent():
    model, deformation, delta_c, matrix = _bend()
    stats: dict = {}
    out = df.apply(deformation, model, delta_c, moving_matrix=matrix, covariance="limited",
                   stats=stats, split="auto")
    return model, deformation, delta_c, matrix, out, stats


def test_split_bend_bounds_and_fixed_rows(bent) -> None:
    model, deformation, delta_c, matrix, out, stats = bent
    n = model.n_points
    assert stats["split_splats"] > 0
    assert out.n_points == n + stats["split_children"] - stats["split_splats"]
    assert stats["split_children"] <= sp.MAX_CHILDREN * stats["split_splats"]
    moved = n - int(deformation.fixed.sum())
    assert out.n_points - n <= sp.GROWTH_CAP * moved
    fixed = deformation.fixed
    g, gi = out.gaussians, model.gaussians
    assert np.array_equal(out.positions[:n][fixed], model.positions[fixed])
    for name in ("scale_log", "rotation", "opacity", "sh_dc"):
        assert getattr(g, name)[:n][fixed].tobytes() == getattr(gi, name)[fixed].tobytes()
    parents = stats["parent_rows"]
    assert parents.size == out.n_points - n and (np.diff(parents) >= 0).all()
    assert not fixed[parents].any() and not deformation.moving[parents].any()
    # the unsplit path leaves the count alone
    off = df.apply(deformation, model, delta_c, moving_matrix=matrix, covariance="limited",
                   split="off")
    assert off.n_points == n
    # on by default (issue 46)
    default = df.apply(deformation, model, delta_c, moving_matrix=matrix, covariance="limited")
    assert default.n_points == out.n_points


def test_split_is_deterministic(bent, tmp_path: Path) -> None:
    model, deformation, delta_c, matrix, out, _ = bent
    again = df.apply(deformation, model, delta_c, moving_matrix=matrix, covariance="limited",
                     split="auto")
    save(out, tmp_path / "a.ply")
    save(again, tmp_path / "b.ply")
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()


def test_split_children_at_rest_render_like_the_parent(bent) -> None:
    """A real render (EGL): the split scene with every child at its rest centre against the
    original (a whole-image PSNR floor for the opacity/colour rule)."""
    from splatdeform.render import View, render_image

    model, deformation, *_ = bent
    rows = deformation.free_idx
    counts = np.ones((rows.size, 3), np.int64)
    counts[:, 0] = 2
    counts[::2, 1] = 2
    kids = sp.children(model, rows, counts)
    rest = sp.take(model, kids.parent)
    rest.positions, rest.gaussians.scale_log = kids.centers, kids.scale_log
    rest.gaussians.opacity = kids.opacity
    keep = np.ones(model.n_points, bool)
    keep[rows] = False
    scene = sp.concat(sp.take(model, np.flatnonzero(keep)), rest)
    view = View(size=(200, 200), azimuth=0.0, elevation=0.0)
    a = render_image(model, view).astype(float)
    b = render_image(scene, view).astype(float)
    mse = ((a - b) ** 2).mean()
    assert 10 * np.log10(255 ** 2 / max(mse, 1e-12)) > 30


@pytest.mark.parametrize("ext", [".ply", ".compressed.ply", ".spz", ".sog", ".glb"])
def test_every_writer_takes_the_larger_count(bent, tmp_path: Path, ext: str) -> None:
    out = bent[4]
    path = tmp_path / f"split{ext}"
    save(out, path)
    back = load(path)
    assert back.n_points == out.n_points > bent[0].n_points


def test_split_mode_is_checked(bent) -> None:
    from splatdeform.errors import InputError

    model, deformation, delta_c, matrix, *_ = bent
    with pytest.raises(InputError, match="gaussians.split"):
        df.apply(deformation, model, delta_c, moving_matrix=matrix, split="always")


def test_closed_forms_match_lapack() -> None:
    """plan()'s determinant and largest singular value without a per-splat LAPACK call."""
    rng = np.random.default_rng(11)
    mats = rng.normal(size=(500, 3, 3))
    mats[:50] = np.eye(3) * rng.uniform(0.1, 3, (50, 1, 1))  # equal singular values
    mats[50:100, :, 2] = 0  # rank 2
    assert np.allclose(sp._det3(mats), np.linalg.det(mats), rtol=1e-12, atol=1e-12)
    top = np.linalg.svd(mats, compute_uv=False)[:, 0]
    assert np.allclose(sp._largest_singular(mats), top, rtol=1e-9)
    assert sp._largest_singular(np.zeros((0, 3, 3))).shape == (0,)


@pytest.mark.parametrize("backend", ["numpy", "opencl"])
def test_an_affine_fit_field_never_splits_exactly(bent, backend: str) -> None:
    """A real fit whose RBF weights are zero (only its polynomial part: an affine field that
    stretches 3x) gives a bend term of exactly 0 on either backend, so nothing splits, whatever
    float32 differences the backend's rounding would show."""
    from dataclasses import replace

    model, deformation, *_ = bent
    fit = deformation.fit
    weights = np.zeros_like(fit.weights)
    weights[1:4, :3] = np.diag([3.0, 1.0, 1.0]) * fit.normalization.scale  # x -> 4x
    affine = replace(fit, weights=weights)
    delta = np.eye(fit.k, 3)
    field = sp.FitField(affine, delta, backend=backend)
    rows = deformation.free_idx
    sigma, rot = sp._frames(model.gaussians.scale_log[rows], model.gaussians.rotation[rows])
    curv = field.curvature(model.positions[rows], sigma, rot)
    assert (curv == 0).all()
    _, jac = field(model.positions[rows], True)
    assert np.allclose(jac[:, 0, 0], 4.0, rtol=1e-5)
    assert not sp.plan(model.gaussians.scale_log[rows], model.gaussians.rotation[rows], jac,
                       curv).split.any()


def test_opencl_and_numpy_fields_split_alike(bent) -> None:
    """The sigma points and children through OpenCL float32 give the float64 reference's split
    decisions on the bend, and children within float32 rounding of it."""
    model, deformation, delta_c, *_ = bent
    rows = deformation.free_idx
    g = model.gaussians
    sigma, rot = sp._frames(g.scale_log[rows], g.rotation[rows])
    plans, moved = [], []
    for backend in ("numpy", "opencl"):
        field = sp.FitField(deformation.fit, delta_c, backend=backend)
        pos, jac = field(model.positions[rows], True)
        plans.append(sp.plan(g.scale_log[rows], g.rotation[rows], jac,
                             field.curvature(model.positions[rows], sigma, rot)))
        moved.append(pos)
    assert plans[0].split.sum() > 0
    assert (plans[0].counts != plans[1].counts).any(axis=1).sum() <= 2
    assert np.allclose(moved[0], moved[1], atol=1e-5)


def test_editor_save_splits_like_deform_byte_for_byte(tmp_path: Path) -> None:
    """Split on by default: the editor's Save (one-shot deferred basis) and ``deform`` on the
    saved YAML write the same bytes, children included."""
    from splatdeform.deform.handle import compose_transform
    from splatdeform.edit.run import run_edit
    from splatdeform.edit.selectors import Box
    from splatdeform.editor import EditorController

    model = gaussian_bar(3000, seed=6)
    model.gaussians.scale_log += np.float32(np.log(4.0))  # splats big enough to split
    src = tmp_path / "splats.ply"
    save(model, src)
    ed = EditorController.open(src)
    ed.add_selector("fixed", Box((-1.0, -1.0, -1.0), (1.6, 1.0, 1.0)))
    ed.add_selector("handle", Box((2.4, -1.0, -1.0), (5.0, 1.0, 1.0)))
    ed.settings.fit.tolerance = 1e-3
    ed.fit()
    ed.set_pose(compose_transform(pivot=np.array([2.4, 0.0, 0.0]), axis=(0, 0, 1),
                                  degrees=80))
    saved = ed.save(image=False)
    again = run_edit(saved.config, output=tmp_path / "again.ply")
    assert again.stats["split_splats"] > 0
    assert (tmp_path / "again.ply").read_bytes() == saved.model.read_bytes()
    assert load(saved.model).n_points > model.n_points


def test_streamed_splat_edit_splits(tmp_path: Path) -> None:
    """Streamed edits split too (issue 46 item 3; tests/test_stream_split.py: the in-memory
    file byte for byte): the header counts the children, no warning line."""
    from splatdeform.edit.stream import run_stream

    model = gaussian_bar(6000, seed=2)
    model.gaussians.scale_log += np.float32(np.log(4.0))
    save(model, tmp_path / "x.ply")
    cfg = parse_edit({
        "input": "x.ply", "output": "y.ply",
        "regions": {"units": "relative",
                    "fixed": [{"box": {"min": [0, 0, 0], "max": [0.4, 1, 1]}}],
                    "handle": [{"box": {"min": [0.6, 0, 0], "max": [1, 1, 1]}}]},
        "handle": {"transform": {"pivot": [0.6, 0.5, 0.5],
                                 "rotate": {"axis": [0, 0, 1], "degrees": 90}}},
        "fit": {"tolerance": 2e-3, "max_centers": 600}}, "test")
    result = run_stream(cfg, tmp_path, output=tmp_path / "y.ply", chunk=1_500, quiet=True)
    assert result.stats["split_splats"] > 0 and "split_note" not in result.stats
    assert load(tmp_path / "y.ply").n_points == \
        model.n_points + result.stats["split_children"] - result.stats["split_splats"]


def test_a_stored_basis_keeps_the_sigma_points_basis_once_per_fit(bent) -> None:
    """With a stored basis (the editor, --reuse, poses in turn) the sigma points' RBF basis is
    computed once per fit and each pose is one product; it agrees with one-shot evaluation."""
    from splatdeform.deform.split_field import FitField, fit_field

    model, deformation, delta_c, *_ = bent
    kept = deformation._split_sigma_basis  # left by the fixture's apply
    half = df.apply(deformation, model, 0.5 * delta_c, split="auto")
    assert deformation._split_sigma_basis is kept and half.n_points >= model.n_points
    rows = deformation.free_idx
    sigma, rot = sp._frames(model.gaussians.scale_log[rows], model.gaussians.rotation[rows])
    stored = fit_field(deformation, delta_c)
    assert stored.store is deformation
    one_shot = FitField(deformation.fit, delta_c, backend=stored.backend)
    a = stored.curvature(model.positions[rows], sigma, rot)
    b = one_shot.curvature(model.positions[rows], sigma, rot)
    assert np.abs(a - b).max() < 1e-3 * sp.CURVE_LIMIT  # float32 rounding, far below the limit


def test_one_shot_split_keeps_fixed_and_handle_rows(bent) -> None:
    """As ``deform`` runs it (the basis deferred, one-shot): fixed rows bit-identical and in
    order, handle rows as unsplit, children only after the originals."""
    model, deformation, delta_c, matrix, *_ = bent
    cfg = parse_edit({
        "input": "x.ply", "output": "y.ply",
        "regions": {"units": "relative",
                    "fixed": [{"box": {"min": [0, 0, 0], "max": [0.4, 1, 1]}}],
                    "handle": [{"box": {"min": [0.6, 0, 0], "max": [1, 1, 1]}}]},
        "handle": {"transform": {"pivot": [0.6, 0.5, 0.5],
                                 "rotate": {"axis": [0, 0, 1], "degrees": 90}}},
        "fit": {"tolerance": 2e-3, "max_centers": 600}}, "test")
    lazy = precompute(cfg, model, Path("."), stored=False)
    delta, mat = plain.control_displacement(cfg, model, lazy)
    stats: dict = {}
    out = df.apply(lazy, model, delta, moving_matrix=mat, stats=stats)
    off = df.apply(lazy, model, delta, moving_matrix=mat, split="off")
    n = model.n_points
    assert stats["split_splats"] > 0 and out.n_points > n
    keep = ~np.isin(np.arange(n), stats["parent_rows"]) & ~np.isin(
        np.arange(n), lazy.free_idx)
    for name in ("scale_log", "rotation", "opacity", "sh_dc"):
        assert getattr(out.gaussians, name)[:n][keep].tobytes() == \
            getattr(off.gaussians, name)[keep].tobytes()
    assert out.positions[:n][keep].tobytes() == off.positions[keep].tobytes()
    fixed = lazy.fixed
    assert out.positions[:n][fixed].tobytes() == model.positions[fixed].tobytes()
