"""``gaussians.covariance`` modes (issue 22): one numpy float64 implementation
(splatdeform/deform/gaussians.py) and one in the Gaussian vertex stage (shaders/covariance.glsl),
held together here.

- Parity: for random splats and Jacobians (mild, strongly stretching, folded), the shader's
  deformed covariance (transform feedback on the real EGL context) equals the numpy one to float32
  accuracy, in every mode; ``rotation`` refuses det J <= 0 (covariance kept) and counts it.
- Properties: ``rotation`` keeps each splat's shape (axis ratios) and scales its volume by
  det J^2; ``limited`` keeps det(Sigma') = det(J Sigma J^T) and the anisotropy growth
  <= ANISOTROPY_GROWTH; SH follow the same polar rotation in every mode.
- Needles: under a strong stretch of a generated scene of round splats, ``jacobian`` makes
  splats whose largest/smallest axis ratio grew more than 4x, the default mode none.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import egl_renderer
from fixtures import random_jacobians, random_splats

from splatdeform.deform.gaussians import (
    ANISOTROPY_GROWTH,
    COVARIANCE_MODES,
    deform_gaussians,
)
from splatdeform.render.gaussian_data import covariances, log_scale_shape
from splatdeform.resources import resource_path

DEFAULT_MODE = "limited"  # README "Gaussian splats: covariance modes"; benchmarks/bench_needles.py

HARNESS = """
in vec3 in_j0; in vec3 in_j1; in vec3 in_j2; in vec3 in_cov_a; in vec3 in_cov_b;
in vec2 in_shape;
out vec3 o_cov_a; out vec3 o_cov_b;
void main() {
    mat3 J = mat3(in_j0, in_j1, in_j2);
    mat3 S = mat3(in_cov_a.x, in_cov_a.y, in_cov_a.z, in_cov_a.y, in_cov_b.x, in_cov_b.y,
                  in_cov_a.z, in_cov_b.y, in_cov_b.z);
    mat3 D = deform_covariance(J, S, in_shape);
    o_cov_a = vec3(D[0][0], D[0][1], D[0][2]);
    o_cov_b = vec3(D[1][1], D[1][2], D[2][2]);
    gl_Position = vec4(0.0, 0.0, 0.0, 1.0);
}
"""


def shader_covariances(mode: str, sigma: np.ndarray, jac: np.ndarray, shape: np.ndarray
                       ) -> np.ndarray:
    """Sigma' (M, 3, 3) from covariance.glsl (float32, transform feedback); shape (M, 2): the
    input log-scales' spread and mean, as the renderer uploads them."""
    renderer = egl_renderer((8, 8))
    ctx = renderer.ctx
    src = ("#version 330 core\n"
           f"#define COVARIANCE {COVARIANCE_MODES.index(mode)}\n"
           + resource_path("shaders", "covariance.glsl").read_text() + HARNESS)
    prog = ctx.program(vertex_shader=src, varyings=["o_cov_a", "o_cov_b"])
    m = sigma.shape[0]
    cols = jac.transpose(0, 2, 1).reshape(m, 9)  # columns of J
    tri = np.stack([sigma[:, 0, 0], sigma[:, 0, 1], sigma[:, 0, 2],
                    sigma[:, 1, 1], sigma[:, 1, 2], sigma[:, 2, 2]], axis=1)
    data = np.ascontiguousarray(np.concatenate([cols, tri, shape], axis=1), dtype=np.float32)
    vbo = ctx.buffer(data.tobytes())
    out = ctx.buffer(reserve=m * 6 * 4)
    vao = ctx.vertex_array(prog, [(vbo, "3f 3f 3f 3f 3f 2f", "in_j0", "in_j1", "in_j2",
                                   "in_cov_a", "in_cov_b", "in_shape")], skip_errors=True)
    try:
        renderer.targets.ms.use()
        vao.transform(out, mode=ctx.POINTS, vertices=m)
        got = np.frombuffer(out.read(), dtype=np.float32).reshape(m, 6).astype(np.float64)
    finally:
        for obj in (vao, vbo, out, prog):
            obj.release()
        renderer.release()
    a, b, c, d, e, f = got.T
    return np.stack([np.stack([a, b, c], -1), np.stack([b, d, e], -1),
                     np.stack([c, e, f], -1)], axis=1)


@pytest.mark.parametrize("mode", COVARIANCE_MODES)
def test_shader_matches_numpy(mode):
    scale_log, quat = random_splats(400)
    jac = random_jacobians(400)
    new = deform_gaussians(scale_log, quat, None, jac, covariance=mode)
    want = covariances(new.scale_log, new.rotation)
    got = shader_covariances(mode, covariances(scale_log, quat), jac, log_scale_shape(scale_log))
    norm = np.linalg.norm(want, axis=(1, 2))
    err = np.linalg.norm(got - want, axis=(1, 2)) / norm
    # float32: 1e-4 relative where J Sigma J^T is well conditioned; the float32 eigen-solve of
    # ``limited`` loses the smallest axis of a near-singular one in proportion to its condition
    sj = jac @ covariances(scale_log, quat) @ jac.transpose(0, 2, 1)
    ev = np.linalg.eigvalsh(sj)
    cond = ev[:, 2] / np.maximum(np.abs(ev[:, 0]), 1e-300)
    assert err[cond < 1e4].max() <= 1e-4, f"{mode}: shader vs numpy {err[cond < 1e4].max():.3g}"
    assert (err <= 1e-4 + 1e-8 * cond).all(), f"{mode}: shader vs numpy {err.max():.3g}"
    folded = int((np.linalg.det(jac) <= 0).sum())
    assert folded >= 8 and new.refused == (folded if mode == "rotation" else 0)


def axis_ratio(scale_log: np.ndarray) -> np.ndarray:
    return np.exp(np.ptp(np.asarray(scale_log, np.float64), axis=1))


def test_mode_properties():
    scale_log, quat = random_splats(300, seed=3)
    jac = random_jacobians(300, seed=4)
    keep = np.linalg.det(jac) > 0.05  # not folded (rotation refuses those)
    jac, scale_log, quat = jac[keep], scale_log[keep], quat[keep]
    sigma_j = jac @ covariances(scale_log, quat) @ jac.transpose(0, 2, 1)
    rot = deform_gaussians(scale_log, quat, None, jac, covariance="rotation")
    np.testing.assert_allclose(np.sort(rot.scale_log - rot.scale_log.mean(1, keepdims=True), 1),
                               np.sort(scale_log - scale_log.mean(1, keepdims=True), 1),
                               atol=1e-12)
    det_j = np.linalg.det(covariances(rot.scale_log, rot.rotation))
    np.testing.assert_allclose(det_j, np.linalg.det(sigma_j), rtol=1e-9)
    lim = deform_gaussians(scale_log, quat, None, jac, covariance="limited")
    np.testing.assert_allclose(np.linalg.det(covariances(lim.scale_log, lim.rotation)),
                               np.linalg.det(sigma_j), rtol=1e-9)
    growth = axis_ratio(lim.scale_log) / axis_ratio(scale_log)
    assert growth.max() <= ANISOTROPY_GROWTH * (1 + 1e-9)
    jacobian = deform_gaussians(scale_log, quat, None, jac, covariance="jacobian")
    assert (axis_ratio(jacobian.scale_log) / axis_ratio(scale_log)).max() > 4  # exercised


@pytest.mark.parametrize("mode", COVARIANCE_MODES)
def test_sh_follow_the_polar_rotation_in_every_mode(mode):
    scale_log, quat = random_splats(50, seed=5)
    jac = random_jacobians(50, seed=6)
    sh = np.random.default_rng(7).normal(size=(50, 45))
    base = deform_gaussians(scale_log, quat, sh, jac)
    new = deform_gaussians(scale_log, quat, sh, jac, covariance=mode)
    np.testing.assert_array_equal(new.sh_rest, base.sh_rest)
    np.testing.assert_array_equal(new.rotation_matrix, base.rotation_matrix)


def test_default_mode_makes_no_needles_under_a_strong_stretch():
    """Round splats (ratio 1) on a bar, stretched along x by 3x with shear (J varies per splat):
    the default mode leaves no splat whose anisotropy grew by more than 4x."""
    rng = np.random.default_rng(11)
    n = 2000
    scale_log = np.full((n, 3), -3.0) + rng.uniform(-0.05, 0.05, (n, 3))
    quat = rng.normal(size=(n, 4))
    s = rng.uniform(0, 1, n)
    jac = np.tile(np.eye(3), (n, 1, 1))
    jac[:, 0, 0] = 1 + 3 * s
    jac[:, 0, 1] = 1.5 * s
    ratio_in = axis_ratio(scale_log)
    needles = {}
    for mode in COVARIANCE_MODES:
        new = deform_gaussians(scale_log, quat, None, jac, covariance=mode)
        needles[mode] = int((axis_ratio(new.scale_log) / ratio_in > 4).sum())
    assert needles["jacobian"] > 100
    assert needles[DEFAULT_MODE] == 0


@pytest.mark.parametrize("mode", COVARIANCE_MODES)
def test_vertex_stage_renders_each_mode_like_the_cpu(mode):
    """The Gaussian vertex stage with ``covariance=mode`` against the numpy reference
    rasteriser of the same splats deformed on the CPU by that mode (PSNR >= 35 dB); a strong
    random smooth field, so ``limited`` and ``rotation`` differ from ``jacobian`` there."""
    from conftest import shared_file
    from fixtures import cut, smooth_basis, to_uint8
    from splat_reference import psnr, reference_render

    SIZE = (128, 128)   # the render tests' panel

    from splatdeform.deform.arrays import displace, jacobians
    from splatdeform.io import load
    from splatdeform.model import Gaussians, PointModel
    from splatdeform.render.camera import View, frame_points

    scene = cut(load(shared_file("splats/guitar_3dgs_sh0.ply")), 2500)
    values, gradients = smooth_basis(scene.positions, seed=5)
    delta_c = np.random.default_rng(6).normal(size=(4, 3)) * 0.3 * scene.diagonal()
    g = scene.gaussians
    jac = jacobians(gradients.astype(np.float64), delta_c)
    new = deform_gaussians(g.scale_log.astype(np.float64), g.rotation.astype(np.float64), None,
                           jac, covariance=mode)
    moved = PointModel(positions=displace(scene.positions, values.astype(np.float64), delta_c),
                       kind="gaussians",
                       gaussians=Gaussians(new.scale_log, new.rotation, g.opacity, g.sh_dc, None))
    camera = frame_points([scene.positions, moved.positions],
                          View(azimuth=20, elevation=15, up="-y"))
    renderer = egl_renderer(SIZE)
    try:
        gpu = renderer.upload(scene, values, gradients, covariance=mode)
        try:
            after = renderer.draw(gpu, camera, delta_c)
        finally:
            gpu.release()
    finally:
        renderer.release()
    want = to_uint8(reference_render(moved, camera, SIZE))
    assert psnr(after, want) >= 35.0
    if mode != "jacobian":
        plain = deform_gaussians(g.scale_log.astype(np.float64), g.rotation.astype(np.float64),
                                 None, jac, covariance="jacobian")
        assert np.abs(plain.scale_log - new.scale_log).max() > 0.5  # the mode mattered here
