"""Handle deformations end to end, checked against independent oracles.

Oracles: affine coordinates solved here from the frame's 4x4 system, the 4x4 handle matrix
applied directly, central finite differences of the field, normals re-estimated by local PCA of
the deformed points, local tangent-area change of k-nearest-neighbour patches, the linearity of
the precomputed basis. Never numbers copied from our own output. Every RNG is seeded.
"""

from __future__ import annotations

import dataclasses
import re
from functools import partial
from pathlib import Path

import helpers
import numpy as np
import pytest
import yaml
from conftest import ROOT, shared_file
from scipy.spatial import cKDTree

import splatdeform as sd
from data_tools.synth import bumpy_bar, sphere
from splatdeform.basis import compute_basis
from splatdeform.basis.reference import compute_basis as reference_basis
from splatdeform.deform import constraint_error
from splatdeform.deform.arrays import jacobians
from splatdeform.rbf import Normalization, fit_incremental

TOL = 1e-4
NUMPY_BASIS = partial(compute_basis, gradients=False, backend="numpy")


# ----------------------------------------------------------------------------- helpers

def affine_matrix(linear: np.ndarray, offset) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = offset
    return m


def apply_matrix(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Homogeneous 4x4 product written out here (not the package's apply_affine)."""
    hom = np.hstack([points, np.ones((points.shape[0], 1))])
    return (hom @ matrix.T)[:, :3]


def rot(axis, degrees) -> np.ndarray:
    """Rodrigues rotation via the matrix exponential of the cross-product matrix."""
    from scipy.linalg import expm

    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return expm(np.radians(degrees) * k)


def about_pivot(linear, pivot, translate=(0, 0, 0)) -> np.ndarray:
    pivot = np.asarray(pivot, float)
    return affine_matrix(linear, pivot + np.asarray(translate, float) - linear @ pivot)


def affine_coords(control: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Affine coordinates (M, 4) solved from [C^T; 1] m = [p; 1] (independent of the package)."""
    system = np.vstack([control.T, np.ones(4)])
    rhs = np.vstack([points.T, np.ones(points.shape[0])])
    return np.linalg.solve(system, rhs).T


def pca_normals(points: np.ndarray, k: int = 16) -> np.ndarray:
    """Unoriented normals by local PCA over the k nearest neighbours."""
    _, nbr = cKDTree(points).query(points, k=k)
    nb = points[nbr] - points[nbr].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, vecs = np.linalg.eigh(cov)
    return vecs[:, :, 0]


def tangent_area(points: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    """Area measure sqrt(l1 l2) of each neighbourhood (two largest covariance eigenvalues)."""
    nb = points[nbr] - points[nbr].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    w = np.linalg.eigvalsh(cov)
    return np.sqrt(w[:, 1] * w[:, 2])


def check_handle_edit(model, d, matrix, out, *, overshoot=1.05):
    """F bit-exact, H = T(h), no NaN, free points bounded by the affine map's displacement."""
    diag = model.diagonal()
    assert np.isfinite(out.positions).all()
    assert np.array_equal(out.positions[d.fixed], model.positions[d.fixed])
    want_h = apply_matrix(matrix, model.positions[d.moving])
    assert np.abs(out.positions[d.moving] - want_h).max() <= 1e-12 * diag
    disp = np.linalg.norm(out.positions - model.positions, axis=1)
    # the field blends 0 (F) into T(x) - x (H); bound: the larger of the handle's own move and
    # what the affine map would do at the free points
    t_free = np.linalg.norm(apply_matrix(matrix, model.positions[d.free_idx])
                            - model.positions[d.free_idx], axis=1)
    bound = max(disp[d.moving].max(), t_free.max())
    ratio = disp[d.free_idx].max() / bound
    print(f"free/handle displacement ratio {ratio:.3f}")
    assert ratio <= overshoot, ratio
    return disp


# ----------------------------------------------------------------------------- bar fixture

@pytest.fixture(scope="module")
def bar():
    return bumpy_bar(6000, seed=7)


@pytest.fixture(scope="module")
def bar_masks(bar):
    x = bar.positions[:, 0]
    return x <= 1.0, x >= 3.0


@pytest.fixture(scope="module")
def bar_def(bar, bar_masks):
    fixed, handle = bar_masks
    return sd.prepare_handle(bar, fixed, handle, tolerance=TOL, method="incremental",
                            backend="numpy")


@pytest.fixture(scope="module")
def bend(bar):
    """Rotate 30 degrees about z around the handle's inner end and lift."""
    return about_pivot(rot((0, 0, 1), 30), (3.0, 0, 0), (0, 0.3, 0.1))


# ----------------------------------------------------------------------------- affine reproduction

def test_affine_rhs_on_all_constraints_moves_everything_affinely(bar, bar_def):
    d = bar_def
    control = d.control_points
    rhs = affine_coords(control, d.constraint_points)  # F rows too: an affine field everywhere
    fit = fit_incremental(d.constraint_points, rhs, tolerance=TOL,
                          normalization=Normalization.of(bar.positions))
    assert fit.converged
    assert fit.n_centers == 0  # the linear part alone reproduces affine coordinates
    basis_all = reference_basis(bar.positions, fit, gradients=True)
    want = affine_coords(control, bar.positions)
    assert np.abs(basis_all.values - want).max() <= 1e-9 * np.abs(want).max()
    # through apply(): the free region and the handle move by one arbitrary affine map
    rng = np.random.default_rng(11)
    matrix = affine_matrix(np.eye(3) + 0.3 * rng.standard_normal((3, 3)), rng.normal(size=3))
    d2 = dataclasses.replace(d, fit=fit, basis=reference_basis(bar.positions[d.free_idx], fit))
    out = sd.apply(d2, bar, sd.delta_for(d2, matrix))
    moved = ~d.fixed
    want_pos = apply_matrix(matrix, bar.positions[moved])
    err = np.abs(out.positions[moved] - want_pos).max()
    assert err <= 1e-9 * bar.diagonal(), err
    assert np.array_equal(out.positions[d.fixed], bar.positions[d.fixed])


def test_handle_frame_coordinates_are_affine(bar, bar_def):
    d = bar_def
    want = affine_coords(d.control_points, bar.positions[d.moving_idx])
    np.testing.assert_allclose(d.moving_coords, want, atol=1e-10)
    np.testing.assert_allclose(d.moving_coords.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(d.moving_coords @ d.control_points, bar.positions[d.moving_idx],
                               atol=1e-12 * bar.diagonal())


def test_zero_delta_is_bit_identical(bar, bar_def):
    out = sd.apply(bar_def, bar, np.zeros((4, 3)))
    assert np.array_equal(out.positions, bar.positions)
    out = sd.apply(bar_def, bar, np.zeros((4, 3)), moving_matrix=np.eye(4))
    assert np.array_equal(out.positions, bar.positions)
    np.testing.assert_allclose(out.normals, bar.normals, rtol=0, atol=1e-15)
    np.testing.assert_allclose(out.radius, bar.radius, rtol=1e-15)


# ----------------------------------------------------------------------------- region behaviour

def test_fixed_exact_handle_exact_free_smooth(bar, bar_def, bend):
    d = bar_def
    fixed, handle = d.fixed, d.moving
    # the rings are F/H points next to the free region and make up every constraint
    assert set(d.constraint_idx) <= set(np.flatnonzero(fixed | handle))
    assert len(d.ring_sizes[0]) == 3 and len(d.ring_sizes[1]) == 3  # C2 -> 3 rings each
    assert d.fit.n_centers < d.constraint_idx.size
    delta = sd.delta_for(d, bend)
    out = sd.apply(d, bar, delta, moving_matrix=bend)
    disp = check_handle_edit(bar, d, bend, out)
    # constraint (ring) points got their prescribed values: 0 for F, T(h) - h for H
    ring_f = d.constraint_idx[fixed[d.constraint_idx]]
    ring_h = d.constraint_idx[handle[d.constraint_idx]]
    assert ring_f.size and ring_h.size
    assert np.array_equal(out.positions[ring_f], bar.positions[ring_f])
    np.testing.assert_allclose(out.positions[ring_h], apply_matrix(bend, bar.positions[ring_h]),
                               rtol=0, atol=1e-12 * bar.diagonal())
    # handle recovered from delta_c alone (no matrix) is the same affine map
    out2 = sd.apply(d, bar, delta)
    np.testing.assert_allclose(out2.positions[handle], apply_matrix(bend, bar.positions[handle]),
                               rtol=0, atol=1e-12 * bar.diagonal())
    # the field itself meets the constraints: evaluated at the kept ring points (independent
    # of the F/H bookkeeping) it reproduces 0 and T(h) - h to the fit tolerance
    kept = d.kept if d.kept is not None else slice(None)
    pts = d.constraint_points[kept]
    vals = reference_basis(pts, d.fit, gradients=False).values
    field = pts + vals @ delta
    want = np.where(handle[d.constraint_idx[kept]][:, None], apply_matrix(bend, pts), pts)
    assert np.linalg.norm(field - want, axis=1).max() <= TOL * np.abs(delta).sum()
    # smooth: the displacement of neighbouring free points differs little
    free = d.free_idx
    _, nbr = cKDTree(bar.positions[free]).query(bar.positions[free], k=2)
    jump = np.linalg.norm(out.positions[free][nbr[:, 1]] - out.positions[free]
                          - (bar.positions[free][nbr[:, 1]] - bar.positions[free]), axis=1)
    gap = np.linalg.norm(bar.positions[free][nbr[:, 1]] - bar.positions[free], axis=1)
    assert np.all(jump <= 3.0 * gap + 1e-12), (jump / gap).max()
    assert disp[free].max() > 0


def test_pure_translation_free_points_bounded_by_translation(bar, bar_def):
    t = np.array([0.0, 0.4, -0.2])
    matrix = affine_matrix(np.eye(3), t)
    out = sd.apply(bar_def, bar, sd.delta_for(bar_def, matrix), moving_matrix=matrix)
    disp = np.linalg.norm(out.positions - bar.positions, axis=1)
    assert disp[bar_def.free_idx].max() <= 1.02 * np.linalg.norm(t)
    assert np.array_equal(out.positions[bar_def.fixed], bar.positions[bar_def.fixed])


def test_constraint_error_within_design_bound(bar, bar_def, bend):
    """fit.tolerance bounds the error at the kept (thinned) constraints; the reported
    constraint error covers every ring point, kept or not."""
    rng = np.random.default_rng(5)
    kept = bar_def.kept if bar_def.kept is not None else slice(None)
    for delta in (sd.delta_for(bar_def, bend), rng.normal(scale=0.5, size=(4, 3))):
        values = NUMPY_BASIS(bar_def.constraint_points, bar_def.fit).values
        dist = np.linalg.norm((values - bar_def.constraint_rhs) @ delta, axis=1)
        bound = TOL * np.linalg.norm(delta, axis=1).sum()
        assert 0 <= dist[kept].max() <= bound, (dist[kept].max(), bound)
        assert constraint_error(bar_def, delta, NUMPY_BASIS) == pytest.approx(dist.max(),
                                                                              rel=1e-12)


def test_jacobian_matches_central_differences(bar, bar_def, bend):
    d = bar_def
    delta = sd.delta_for(d, bend)
    rng = np.random.default_rng(3)
    pick = rng.choice(d.free_idx.size, 60, replace=False)
    pts = bar.positions[d.free_idx[pick]]
    jac = jacobians(d.basis.gradients[pick], delta)

    def field(x):
        return x + reference_basis(x, d.fit, gradients=False).values @ delta

    h = 1e-4 * bar.diagonal()
    fd = np.empty_like(jac)
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        fd[:, :, axis] = (field(pts + step) - field(pts - step)) / (2 * h)
    assert np.abs(jac - fd).max() <= 1e-6, np.abs(jac - fd).max()
    # and the deformation is far from the identity there (the test means something)
    assert np.abs(fd - np.eye(3)).max() > 0.05
    # deformed normals = normalize(J^-T n) (explicit inverse here, cofactor in the package)
    out = sd.apply(d, bar, delta, moving_matrix=bend)
    n = bar.normals[d.free_idx[pick]]
    want = np.einsum("nji,nj->ni", np.linalg.inv(fd), n)
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    np.testing.assert_allclose(out.normals[d.free_idx[pick]], want, atol=1e-6)


def test_normals_follow_the_surface_on_dense_sphere():
    model = sphere(20000, seed=2)
    z = model.positions[:, 2]
    fixed, handle = z <= -0.2, z >= 0.7
    d = sd.prepare_handle(model, fixed, handle, tolerance=TOL, backend="numpy", neighbors=8)
    assert d.fit.converged
    matrix = about_pivot(rot((0, 0, 1), 30) @ np.diag([1.2, 1.2, 1.0]),
                         model.positions[handle].mean(0), (0, 0, 0.4))
    out = sd.apply(d, model, sd.delta_for(d, matrix), moving_matrix=matrix)
    check_handle_edit(model, d, matrix, out, overshoot=1.05)
    est = pca_normals(out.positions)
    # orient the PCA normals by the input normals (the edit tilts normals well under 90 deg)
    est *= np.sign(np.einsum("ij,ij->i", est, model.normals))[:, None]
    free = d.free_idx
    cos = np.einsum("ij,ij->i", out.normals[free], est[free])
    angles = np.degrees(np.arccos(np.clip(np.abs(cos), 0, 1)))
    assert np.median(angles) < 2.0, np.median(angles)
    assert np.percentile(angles, 95) < 6.0, np.percentile(angles, 95)
    assert (cos > 0).mean() > 0.995
    # the edit did change the normals noticeably (else the test says nothing)
    tilt = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", out.normals[free],
                                                  model.normals[free]), -1, 1)))
    assert np.percentile(tilt, 90) > 5.0
    # handle normals: rotated and scaled exactly like T's cofactor
    lin = matrix[:3, :3]
    want_h = model.normals[handle] @ np.linalg.inv(lin)
    want_h /= np.linalg.norm(want_h, axis=1, keepdims=True)
    np.testing.assert_allclose(out.normals[handle], want_h, atol=1e-12)


# ----------------------------------------------------------------------------- radius-only surfels

def test_radius_only_surfels(bar, bar_def, bend):
    d = bar_def
    assert bar.kind == "surfel_radius" and bar.axes is None
    out = sd.apply(d, bar, sd.delta_for(d, bend), moving_matrix=bend)
    assert out.axes is None
    assert np.array_equal(out.radius[d.fixed], bar.radius[d.fixed])
    # rigid handle motion keeps the handle's radii
    np.testing.assert_allclose(out.radius[d.moving], bar.radius[d.moving], rtol=1e-12)
    # free points: radius ratio = sqrt(area ratio) of the local tangent patch
    free = d.free_idx
    _, nbr = cKDTree(bar.positions).query(bar.positions[free], k=16)
    area_ratio = tangent_area(out.positions, nbr) / tangent_area(bar.positions, nbr)
    ratio = out.radius[free] / bar.radius[free]
    rel = np.abs(ratio / np.sqrt(area_ratio) - 1)
    assert np.median(rel) < 0.01, np.median(rel)
    assert np.percentile(rel, 95) < 0.05, np.percentile(rel, 95)
    assert np.abs(ratio - 1).max() > 0.02  # the field stretches somewhere

    # uniform scaling of the handle scales its radii by s (area s^2)
    scale = about_pivot(1.5 * np.eye(3), bar.positions[d.moving].mean(0))
    out = sd.apply(d, bar, sd.delta_for(d, scale), moving_matrix=scale)
    np.testing.assert_allclose(out.radius[d.moving], 1.5 * bar.radius[d.moving], rtol=1e-12)
    assert np.array_equal(out.radius[d.fixed], bar.radius[d.fixed])


def test_translation_keeps_fixed_and_handle_radii(bar, bar_def):
    d = bar_def
    matrix = affine_matrix(np.eye(3), (0.2, 0.3, -0.1))
    out = sd.apply(d, bar, sd.delta_for(d, matrix), moving_matrix=matrix)
    assert np.array_equal(out.radius[d.fixed], bar.radius[d.fixed])
    np.testing.assert_allclose(out.radius[d.moving], bar.radius[d.moving], rtol=1e-12)
    np.testing.assert_allclose(out.normals[d.moving], bar.normals[d.moving], atol=1e-12)
    # a translation of the whole model (every point a handle point) keeps every radius
    everywhere = dataclasses.replace(
        d, moving=np.ones(bar.n_points, bool), moving_idx=np.arange(bar.n_points),
        free_idx=np.zeros(0, np.int64),
        moving_coords=affine_coords(d.control_points, bar.positions),
        moving_gradients=np.broadcast_to(d.moving_gradients[0], (bar.n_points, 4, 3)),
        basis=dataclasses.replace(d.basis, values=np.zeros((0, 4)),
                                  gradients=np.zeros((0, 4, 3))))
    out = sd.apply(everywhere, bar, sd.delta_for(d, matrix))
    np.testing.assert_allclose(out.radius, bar.radius, rtol=1e-12)
    np.testing.assert_allclose(out.positions, bar.positions + [0.2, 0.3, -0.1], atol=1e-12)


# ----------------------------------------------------------------------------- many delta_c

def test_apply_is_linear_and_reusable(bar, bar_masks, bar_def, bend):
    d = bar_def
    rng = np.random.default_rng(8)
    d1, d2 = sd.delta_for(d, bend), rng.normal(scale=0.2, size=(4, 3))
    free = d.free_idx

    def disp(delta):
        return sd.apply(d, bar, delta).positions[free] - bar.positions[free]

    np.testing.assert_allclose(disp(d1) + disp(d2), disp(d1 + d2), rtol=0,
                               atol=1e-12 * bar.diagonal())
    np.testing.assert_allclose(disp(2.5 * d2), 2.5 * disp(d2), rtol=0,
                               atol=1e-12 * bar.diagonal())
    # many delta_c on one deformation == fresh runs
    fixed, handle = bar_masks
    fresh = sd.prepare_handle(bar, fixed, handle, tolerance=TOL, method="incremental",
                              backend="numpy")
    for _ in range(3):
        delta = rng.normal(scale=0.3, size=(4, 3))
        a = sd.apply(d, bar, delta)
        b = sd.apply(fresh, bar, delta)
        np.testing.assert_allclose(a.positions, b.positions, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.normals, b.normals, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- real data

def _real_edit(model, fixed, handle, matrix, backend):
    d = sd.prepare_handle(model, fixed, handle, tolerance=TOL, backend=backend)
    delta = sd.delta_for(d, matrix)
    out = sd.apply(d, model, delta, moving_matrix=matrix)
    check_handle_edit(model, d, matrix, out, overshoot=1.05)
    assert d.fit.converged and d.fit.n_centers <= d.constraint_idx.size
    err = constraint_error(d, delta, NUMPY_BASIS)
    assert err <= TOL * np.linalg.norm(delta, axis=1).sum()
    if out.normals is not None:
        assert np.isfinite(out.normals).all()
    return d, out, err


def test_bunny_bend_ear():
    model = sd.load(shared_file("scans/bunny.ply"))
    p = model.positions
    top = np.argmax(p[:, 1])
    near = np.linalg.norm(p - p[top], axis=1) <= 0.01
    tip = p[near][np.argmax(p[near, 1])]  # the ear tip: highest point in a small sphere
    dist = np.linalg.norm(p - tip, axis=1)
    handle = dist <= 0.015
    mid = 0.5 * (p[:, 1].min() + p[:, 1].max())
    # bottom half, plus everything away from this ear (keeps the other ear out of the free band)
    fixed = (p[:, 1] <= mid) | (dist >= 0.045)
    matrix = about_pivot(rot((1, 0, 0), 20), p[handle].mean(0), (0.005, 0, 0))
    d, out, err = _real_edit(model, fixed, handle, matrix, "numpy")
    print(f"bunny ear: constraints {d.constraint_idx.size} centers {d.fit.n_centers} "
          f"error/diag {err / model.diagonal():.2e}")


def test_armadillo_lift_leg():
    model = sd.load(shared_file("scans/armadillo_oriented.ply"))
    p = model.positions
    lo, hi = model.bbox()
    assert hi[1] - lo[1] > hi[0] - lo[0]  # y is up; the two legs separate along z
    leg = (p[:, 1] < lo[1] + 42) & (p[:, 2] < 22)   # the leg with its foot near z in [-1, 21]
    handle = leg & (p[:, 1] <= lo[1] + 15)           # its lowest points
    fixed = ~leg                                     # the rest of the body stays put
    assert 200 < handle.sum() < 2000
    matrix = about_pivot(rot((1, 0, 0), -15), p[handle].mean(0), (0, 12, -5))
    d, out, err = _real_edit(model, fixed, handle, matrix, "auto")
    assert np.isfinite(out.normals).all()
    print(f"armadillo leg: constraints {d.constraint_idx.size} centers {d.fit.n_centers} "
          f"error/diag {err / model.diagonal():.2e}")


# ----------------------------------------------------------------------------- CLI and API

def _write_edit(path: Path, translate, degrees, backend="numpy", **extra) -> Path:
    cfg = {
        "input": "../scans/bar.ply",
        "output": "../out/bar_bent.ply",
        "regions": {"units": "model",
                    "fixed": [{"box": {"min": [-1, -1, -1], "max": [1.0, 1, 1]}}],
                    "handle": [{"box": {"min": [3.0, -1, -1], "max": [5, 1, 1]}}]},
        "handle": {"transform": {"pivot": [3.0, 0, 0],
                                 "rotate": {"axis": [0, 0, 1], "degrees": degrees},
                                 "translate": list(translate)}},
        "boundary": {"continuity": 2, "neighbors": 10},
        "fit": {"tolerance": TOL, "max_centers": 2000},
        "backend": backend,
        **extra,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(cfg))
    return path


def _cli(*args, cwd):
    return helpers.run_cli("deform", *args, cwd=cwd, timeout=300)


@pytest.fixture(scope="module")
def bar_file(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    (root / "scans").mkdir()
    sd.save(bumpy_bar(4000, seed=4), root / "scans" / "bar.ply")
    return root


def test_cli_end_to_end(bar_file):
    cfg = _write_edit(bar_file / "cfg" / "edit.yaml", (0, 0.3, 0), 30, backend="auto")
    elsewhere = bar_file / "elsewhere"
    elsewhere.mkdir(exist_ok=True)
    res = _cli(cfg, cwd=elsewhere)  # paths resolve against the config file, not the cwd
    assert res.returncode == 0, res.stderr
    out = bar_file / "out" / "bar_bent.ply"
    assert out.is_file()
    for word in ("points", "free", "constraints", "centers", "largest |r|", "RMS",
                 "constraint error"):
        assert word in res.stdout, res.stdout
    lines = res.stdout.splitlines()
    assert any(re.match(r"basis\s+[0-9.]+ s", ln) for ln in lines), res.stdout
    assert any(ln.startswith("fit") for ln in lines)
    src = sd.load(bar_file / "scans" / "bar.ply")
    bent = sd.load(out)
    assert bent.n_points == src.n_points and bent.kind == src.kind
    assert src.source.element("vertex").data.dtype == bent.source.element("vertex").data.dtype
    np.testing.assert_array_equal(bent.colors, src.colors)
    fixed = src.positions[:, 0] <= 1.0
    assert np.array_equal(bent.positions[fixed], src.positions[fixed])
    handle = src.positions[:, 0] >= 3.0
    matrix = about_pivot(rot((0, 0, 1), 30), (3.0, 0, 0), (0, 0.3, 0))
    # PLY stores float32 coordinates: compare at float32 resolution
    np.testing.assert_allclose(bent.positions[handle],
                               apply_matrix(matrix, src.positions[handle]), atol=1e-6)
    assert not np.allclose(bent.positions, src.positions)


def test_cli_reuse_matches_fresh_run(bar_file):
    root = bar_file
    out = root / "reuse" / "bent.ply"
    first = _write_edit(root / "cfg" / "a.yaml", (0, 0.2, 0), 10)
    second = _write_edit(root / "cfg" / "b.yaml", (0, -0.3, 0.1), -25)
    res = _cli(first, "-o", out, "--reuse", cwd=root)
    assert res.returncode == 0, res.stderr
    assert "reused" not in res.stdout
    res = _cli(second, "-o", out, "--reuse", cwd=root)
    assert res.returncode == 0, res.stderr
    assert "reused" in res.stdout, res.stdout
    fresh = root / "reuse" / "fresh.ply"
    res = _cli(second, "-o", fresh, cwd=root)
    assert res.returncode == 0, res.stderr
    a, b = sd.load(out).positions, sd.load(fresh).positions
    scale = np.abs(b).max()
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6 * scale)
    assert not np.allclose(a, sd.load(root / "scans" / "bar.ply").positions)


def test_python_api_docstring_snippet(tmp_path):
    doc = sd.__doc__
    assert "sd.prepare_handle" in doc and "sd.apply" in doc and "sd.save" in doc
    path = tmp_path / "bar.ply"
    sd.save(bumpy_bar(3000, seed=9), path)
    # the docstring's snippet with the bar's coordinates
    model = sd.load(path)
    fixed = sd.select(model, [sd.Box(min=(-1, -1, -1), max=(1, 1, 1))])
    handle = sd.select(model, [sd.Sphere(center=(4.0, 0.0, 0.0), radius=0.9)])
    deformation = sd.prepare_handle(model, fixed, handle, tolerance=1e-4, backend="numpy")
    matrix = sd.compose_transform(pivot=model.positions[handle].mean(0), axis=(0, 0, 1),
                                  degrees=30, translate=(0, 0.01, 0))
    bent = sd.apply(deformation, model, sd.delta_for(deformation, matrix),
                    moving_matrix=matrix)
    sd.save(bent, tmp_path / "bar_bent.ply")
    back = sd.load(tmp_path / "bar_bent.ply")
    assert back.n_points == model.n_points
    want = about_pivot(rot((0, 0, 1), 30), model.positions[handle].mean(0), (0, 0.01, 0))
    np.testing.assert_allclose(matrix, want, atol=1e-12)
    np.testing.assert_allclose(back.positions[handle],
                               apply_matrix(want, model.positions[handle]), atol=1e-6)
    assert np.array_equal(back.positions[fixed], model.positions[fixed])


def test_example_configs_parse():
    from splatdeform.edit.config import load_edit

    paths = [p for p in sorted((ROOT / "configs").glob("*.yaml"))
             if "input" in (yaml.safe_load(p.read_text()) or {})]  # edit configs, not batches
    assert paths
    for path in paths:
        cfg = load_edit(path)
        assert cfg.handle is not None or cfg.curve is not None or cfg.points is not None


def test_covariance_frame_is_j_sigma_jt() -> None:
    """The editor's blocked per-frame covariances equal J Sigma J^T built with jacobians() in
    float64 (chunk boundaries inside the points included)."""
    from splatdeform.deform.arrays import covariance_frame, jacobians

    rng = np.random.default_rng(4)
    m, k = 1000, 4
    grads = rng.normal(size=(m, k, 3)).astype(np.float32)
    delta = 0.1 * rng.normal(size=(k, 3))
    a = rng.normal(size=(m, 3, 3))
    sigma = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(3)
    cov6 = sigma.reshape(m, 9)[:, [0, 1, 2, 4, 5, 8]].astype(np.float32)
    got = covariance_frame(grads, delta, cov6, chunk=300)
    j = jacobians(grads.astype(np.float64), delta)
    want = (j @ sigma @ j.transpose(0, 2, 1)).reshape(m, 9)[:, [0, 1, 2, 4, 5, 8]]
    assert got.dtype == np.float32 and got.shape == (m, 6)
    scale = np.abs(want).max(axis=1, keepdims=True)
    assert np.abs(got - want).max() <= 1e-5 * scale.max()
    assert (np.abs(got - want) <= 1e-5 * scale).all()
