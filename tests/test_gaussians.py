"""3D Gaussian splats under deformation: SH rotation and covariance re-factoring.

Oracles written here, independent of the package: the 3DGS ``eval_sh`` transcribed from the
reference implementation (its constants, signs and the channel-major ``f_rest`` layout of its
``load_ply``), SH rotation by least squares on sampled directions per splat, the polar factor from
``scipy.linalg.polar``, covariances J R S^2 R^T J^T formed in float64, det(Sigma') =
det(J)^2 det(Sigma) for the thinnest axes. Every RNG is seeded.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from conftest import shared_file
from scipy.spatial.transform import Rotation

import splatdeform as sd
from splatdeform.deform.gaussians import deform_gaussians, polar_rotation, svd3
from splatdeform.edit.config import parse_edit
from splatdeform.edit.run import run_edit
from splatdeform.errors import InputError
from splatdeform.geometry import (
    band_rotations,
    matrix_to_quaternion,
    quaternion_multiply,
    quaternion_to_matrix,
    rotate_sh_rest,
    sh_degree,
)

F32 = 2.0 ** -24  # float32 unit roundoff

# ----------------------------------------------------------------------------- 3DGS oracle

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396]
SH_C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435]


def eval_sh(deg: int, sh: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """3DGS ``sh_utils.eval_sh``: sh (..., C, (deg+1)^2), unit dirs (..., 3) -> (..., C)."""
    result = SH_C0 * sh[..., 0]
    if deg > 0:
        x, y, z = dirs[..., 0:1], dirs[..., 1:2], dirs[..., 2:3]
        result = result - SH_C1 * y * sh[..., 1] + SH_C1 * z * sh[..., 2] - SH_C1 * x * sh[..., 3]
        if deg > 1:
            xx, yy, zz = x * x, y * y, z * z
            xy, yz, xz = x * y, y * z, x * z
            result = (result + SH_C2[0] * xy * sh[..., 4] + SH_C2[1] * yz * sh[..., 5]
                      + SH_C2[2] * (2.0 * zz - xx - yy) * sh[..., 6]
                      + SH_C2[3] * xz * sh[..., 7] + SH_C2[4] * (xx - yy) * sh[..., 8])
            if deg > 2:
                result = (result + SH_C3[0] * y * (3 * xx - yy) * sh[..., 9]
                          + SH_C3[1] * xy * z * sh[..., 10]
                          + SH_C3[2] * y * (4 * zz - xx - yy) * sh[..., 11]
                          + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[..., 12]
                          + SH_C3[4] * x * (4 * zz - xx - yy) * sh[..., 13]
                          + SH_C3[5] * z * (xx - yy) * sh[..., 14]
                          + SH_C3[6] * x * (xx - 3 * yy) * sh[..., 15])
    return result


def full_sh(dc: np.ndarray, rest: np.ndarray, deg: int) -> np.ndarray:
    """(M, 3) f_dc and (M, 3n) f_rest -> (M, 3, (deg+1)^2) as 3DGS load_ply builds it:
    features_extra.reshape((N, 3, n)) -- channel-major."""
    n = (deg + 1) ** 2 - 1
    return np.concatenate([np.asarray(dc, np.float64)[:, :, None],
                           np.asarray(rest, np.float64).reshape(-1, 3, n)], axis=2)


def colours(deg: int, dc, rest, dirs: np.ndarray) -> np.ndarray:
    """Colour of every splat (M) along every direction: dirs (M, D, 3) -> (M, D, 3)."""
    sh = full_sh(dc, rest, deg)[:, None]  # (M, 1, 3, 16)
    return eval_sh(deg, sh, dirs)


def unit_dirs(rng: np.random.Generator, *shape: int) -> np.ndarray:
    d = rng.standard_normal((*shape, 3))
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def oracle_rotate(rest: np.ndarray, rot: np.ndarray, deg: int, seed: int = 0) -> np.ndarray:
    """Per splat: the coefficients c' with colour(c', R d) = colour(c, d) on 64 sampled directions,
    by least squares (exact: the colour is linear in c)."""
    rng = np.random.default_rng(seed)
    dirs = unit_dirs(rng, 64)
    n = (deg + 1) ** 2 - 1
    eye = np.eye(n + 1)
    out = np.empty((rest.shape[0], 3 * n))
    for i in range(rest.shape[0]):
        basis_d = eval_sh(deg, eye[None], dirs)[:, 1:]  # (64, n): Y_j(d), one "channel" per j
        basis_rd = eval_sh(deg, eye[None], dirs @ rot[i].T)[:, 1:]
        c = np.asarray(rest[i], np.float64).reshape(3, n).T  # (n, 3)
        sol, *_ = np.linalg.lstsq(basis_rd, basis_d @ c, rcond=None)
        out[i] = sol.T.reshape(-1)
    return out


def covariance(scale_log: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Sigma = R S^2 R^T in float64, R from the quaternion written out here (w first)."""
    q = np.asarray(quat, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    rot = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy: scalar last
    s2 = np.exp(2 * np.asarray(scale_log, np.float64))
    return np.einsum("mij,mj,mkj->mik", rot, s2, rot)


def random_splats(rng: np.random.Generator, m: int, deg: int = 3, thin: float = 20.0):
    """float32 log-scales with axis ratios up to e^thin, random unnormalised quaternions,
    N(0, 1) SH coefficients."""
    scale_log = np.stack([rng.uniform(-3, -1, m), rng.uniform(-4, -2, m),
                          rng.uniform(-3 - thin, -3, m)], axis=1).astype(np.float32)
    quat = (rng.standard_normal((m, 4)) * rng.uniform(0.5, 2, (m, 1))).astype(np.float32)
    n = (deg + 1) ** 2 - 1
    rest = rng.standard_normal((m, 3 * n)).astype(np.float32)
    dc = rng.standard_normal((m, 3)).astype(np.float32)
    return scale_log, quat, dc, rest


# ----------------------------------------------------------------------------- SH rotation

@pytest.mark.parametrize("deg", [1, 2, 3])
def test_sh_rigid_rotation_keeps_colour_along_rotated_directions(deg):
    rng = np.random.default_rng(100 + deg)
    m = 64
    _, _, dc, rest = random_splats(rng, m, deg)
    rot = Rotation.random(m, random_state=deg).as_matrix()
    new = rotate_sh_rest(rest, rot)
    assert new.dtype == np.float32 and new.shape == rest.shape
    dirs = unit_dirs(rng, m, 128)
    before = colours(deg, dc, rest, dirs)
    after = colours(deg, dc, new, np.einsum("mij,mdj->mdi", rot, dirs))
    # float32 storage of c': |error| <= u * ||c'|| * ||Y(d)||, ||Y_bands 1..deg(d)||^2 = n/4pi
    bound = 2 * F32 * np.linalg.norm(rest.reshape(m, 3, -1), axis=2) * np.sqrt(
        ((deg + 1) ** 2 - 1) / (4 * np.pi))
    err = np.abs(after - before)
    assert (err <= bound[:, None, :] + 1e-12).all(), (err / bound[:, None, :]).max()
    # and the view-dependent part really changed (a copy would fail the check above)
    assert np.abs(new - rest).max() > 0.1


def test_sh_rotation_matches_least_squares_oracle_and_composes():
    rng = np.random.default_rng(5)
    _, _, _, rest = random_splats(rng, 20, 3)
    rest = rest.astype(np.float64)
    a = Rotation.random(20, random_state=1).as_matrix()
    b = Rotation.random(20, random_state=2).as_matrix()
    got = rotate_sh_rest(rest, a)
    want = oracle_rotate(rest, a, 3)
    np.testing.assert_allclose(got, want, atol=1e-12 * np.abs(rest).max())
    # D(AB) = D(A) D(B), D orthogonal
    np.testing.assert_allclose(rotate_sh_rest(rotate_sh_rest(rest, b), a),
                               rotate_sh_rest(rest, a @ b), atol=1e-12 * np.abs(rest).max())
    for d in band_rotations(a):
        eye = np.broadcast_to(np.eye(d.shape[1]), d.shape)
        np.testing.assert_allclose(d @ d.transpose(0, 2, 1), eye, atol=1e-13)


def test_sh_degree_from_rest_count():
    assert [sh_degree(n) for n in (0, 9, 24, 45)] == [0, 1, 2, 3]
    with pytest.raises(InputError, match="f_rest"):
        sh_degree(10)


# ----------------------------------------------------------------------------- covariances

def test_svd3_reconstructs_and_keeps_tiny_singular_values_relative():
    rng = np.random.default_rng(8)
    m = 500
    a = np.eye(3) + 0.4 * rng.standard_normal((m, 3, 3))  # well conditioned B
    scales = np.exp(rng.uniform(-25, 0, (m, 3)))  # column scales D: ratios up to e^25
    mat = a * scales[:, None, :]
    u, s, v = svd3(mat)
    recon = np.einsum("mij,mj,mkj->mik", u, s, v)
    # column by column relative to that column's own size (absolute error would hide tiny ones)
    col = np.linalg.norm(mat, axis=1, keepdims=True)
    assert (np.abs(recon - mat) <= 1e-13 * col).all()
    np.testing.assert_allclose(u.transpose(0, 2, 1) @ u, np.broadcast_to(np.eye(3), u.shape),
                               atol=1e-13)
    # product of singular values = |det B| prod(D) with det B well conditioned: pins the
    # smallest singular value to relative accuracy (an eigendecomposition of M M^T cannot)
    log_prod = np.log(s).sum(axis=1)
    want = np.log(np.abs(np.linalg.det(a))) + np.log(scales).sum(axis=1)
    assert np.abs(log_prod - want).max() < 1e-12 * 60


def test_polar_rotation_matches_scipy_and_is_proper():
    rng = np.random.default_rng(9)
    jac = np.eye(3) + 0.5 * rng.standard_normal((200, 3, 3))
    jac = jac[np.linalg.det(jac) > 0.05]
    r = polar_rotation(jac)
    want = np.stack([scipy.linalg.polar(j)[0] for j in jac])
    np.testing.assert_allclose(r, want, atol=1e-10)
    mirror = np.diag([1.0, 1.0, -2.0])[None] @ Rotation.random(3, random_state=4).as_matrix()
    assert np.allclose(np.linalg.det(polar_rotation(mirror)), 1.0)


def test_quaternion_helpers_round_trip():
    rots = Rotation.random(50, random_state=3)
    q = matrix_to_quaternion(rots.as_matrix())
    np.testing.assert_allclose(quaternion_to_matrix(q), rots.as_matrix(), atol=1e-14)
    other = Rotation.random(50, random_state=4)
    prod = quaternion_multiply(q, matrix_to_quaternion(other.as_matrix()))
    np.testing.assert_allclose(quaternion_to_matrix(prod), (rots * other).as_matrix(),
                               atol=1e-14)


def test_general_jacobian_reproduces_jsjt_and_keeps_thin_axes():
    rng = np.random.default_rng(12)
    m = 400
    scale_log, quat, _, rest = random_splats(rng, m, 3, thin=21)
    jac = np.eye(3) + 0.3 * rng.standard_normal((m, 3, 3))
    jac = jac[np.linalg.det(jac) > 0.1]
    keep = jac.shape[0]
    s64, q64 = scale_log[:keep].astype(np.float64), quat[:keep].astype(np.float64)
    new = deform_gaussians(s64, q64, rest[:keep], jac, covariance="jacobian")
    assert not new.similarity.any()
    want = jac @ covariance(s64, q64) @ jac.transpose(0, 2, 1)
    got = covariance(new.scale_log, new.rotation)
    rel = np.linalg.norm(got - want, axis=(1, 2)) / np.linalg.norm(want, axis=(1, 2))
    assert rel.max() < 1e-6, rel.max()
    # det(Sigma') = det(J)^2 det(Sigma): the thinnest axis (axis ratios up to e^21) survives
    log_det = new.scale_log.sum(axis=1) - s64.sum(axis=1)
    np.testing.assert_allclose(log_det, np.log(np.linalg.det(jac)), atol=1e-9)
    assert np.isfinite(new.scale_log).all()
    # float32 in, float32 out
    new32 = deform_gaussians(scale_log[:keep], quat[:keep], rest[:keep], jac,
                            covariance="jacobian")
    assert new32.scale_log.dtype == np.float32 and new32.rotation.dtype == np.float32
    np.testing.assert_allclose(new32.scale_log.sum(axis=1) - scale_log[:keep].sum(axis=1),
                               np.log(np.linalg.det(jac)), atol=1e-5)


def test_similarity_composes_directly_and_identity_is_bit_exact():
    rng = np.random.default_rng(13)
    m = 300
    scale_log, quat, _, rest = random_splats(rng, m, 3, thin=22)
    rot = Rotation.random(m, random_state=6).as_matrix()
    factor = np.exp(rng.uniform(-0.5, 0.5, m))
    jac = rot * factor[:, None, None]
    ident = np.arange(m) % 3 == 0
    jac[ident] = np.eye(3)
    new = deform_gaussians(scale_log, quat, rest, jac, covariance="jacobian")
    assert new.similarity[~ident].all()
    # identity J: every field bit-identical
    for got, was in ((new.scale_log, scale_log), (new.rotation, quat), (new.sh_rest, rest)):
        assert np.array_equal(got[ident], was[ident])
    # similarity: log-scales shift by log s exactly (to float32), the frame turns by R
    np.testing.assert_allclose(new.scale_log[~ident] - scale_log[~ident],
                               np.broadcast_to(np.log(factor[~ident])[:, None], (m - ident.sum(),
                                                                                  3)),
                               atol=1e-5)
    np.testing.assert_allclose(quaternion_to_matrix(new.rotation[~ident]),
                               rot[~ident] @ quaternion_to_matrix(quat[~ident]), atol=1e-6)
    # the quaternion keeps its (unnormalised) length
    np.testing.assert_allclose(np.linalg.norm(new.rotation, axis=1),
                               np.linalg.norm(quat, axis=1), rtol=1e-6)
    np.testing.assert_allclose(new.sh_rest[~ident], oracle_rotate(rest[~ident], rot[~ident], 3),
                               atol=4e-6 * np.abs(rest).max())


# ----------------------------------------------------------------------------- real splat edits

def _edit(tmp_path, src, degrees: float):
    """A handle edit through the public pipeline: the low-y 45 % fixed, the high-y 45 % rotated
    about (0, 1, 1) and lifted; the middle band is free. ``gaussians.covariance: jacobian``
    (J Sigma J^T, what these tests check; the modes: test_covariance_modes.py)."""
    cfg = parse_edit({
        "input": str(src), "output": str(tmp_path / f"bent_{src.name}"),
        "regions": {"units": "relative",
                    "fixed": [{"box": {"min": [0, 0, 0], "max": [1, 0.45, 1]}}],
                    "handle": [{"box": {"min": [0, 0.55, 0], "max": [1, 1, 1]}}]},
        "handle": {"transform": {"pivot": [0.5, 0.55, 0.5],
                                 "rotate": {"axis": [0, 1, 1], "degrees": degrees},
                                 "translate": [0, 0.05, 0]}},
        "boundary": {"continuity": 1, "neighbors": 10},
        "fit": {"tolerance": 1e-3, "max_centers": 2000},
        "backend": "auto",
        "gaussians": {"covariance": "jacobian", "split": "off"},  # per-row J (split: test_split)
    }, "test edit")
    return run_edit(cfg, tmp_path)


@pytest.fixture(scope="module")
def tile_edit(tmp_path_factory):
    """The real SH-degree-3 tile (its very thin splats and real geometry). Its f_rest_* are all
    zero in the shared file, which would make every SH check vacuous: a copy with seeded random
    view-dependent coefficients is edited instead (everything else is the file's own)."""
    root = tmp_path_factory.mktemp("tile")
    model = sd.load(shared_file("splats/tile_3dgs_sh3.ply"))
    assert model.gaussians.sh_rest.shape[1] == 45
    rng = np.random.default_rng(31)
    model.gaussians.sh_rest = (0.3 * rng.standard_normal(model.gaussians.sh_rest.shape)
                               ).astype(np.float32)
    src = sd.save(model, root / "tile_sh3_random.ply")
    return _edit(root, src, 45)


@pytest.fixture(scope="module")
def guitar_edit(tmp_path_factory):
    return _edit(tmp_path_factory.mktemp("guitar"), shared_file("splats/guitar_3dgs_sh0.ply"), 30)


def _free_jacobians(res) -> np.ndarray:
    """J of the free points as the pipeline computed it: I + grad d from the one-shot
    evaluation of W delta_c (``deform`` without --reuse), or I + sum_k delta_c[k] (x) grad b_k
    from a stored basis, written out here."""
    from splatdeform.basis.oneshot import DeferredBasis, oneshot_chunks

    basis = res.deformation.basis
    if isinstance(basis, DeferredBasis):  # run_edit applied it before anything stored it
        grads = [g.astype(np.float64) for *_, g in oneshot_chunks(
            basis.points, basis.fit, res.delta_c, backend=basis.backend, device=basis.device)]
        return np.eye(3) + np.concatenate(grads)
    grads = res.deformation.basis.gradients.astype(np.float64)
    return np.eye(3) + np.einsum("ka,nkb->nab", res.delta_c, grads)


def _check_rigid_and_fixed(res):
    g0, g1 = res.model.gaussians, res.deformed.gaussians
    d = res.deformation
    fixed, mov = np.flatnonzero(d.fixed), d.moving_idx
    assert fixed.size > 100 and mov.size > 100
    for a, b in ((g0.scale_log, g1.scale_log), (g0.rotation, g1.rotation),
                 (g0.sh_rest, g1.sh_rest)):
        if a is not None:
            assert np.array_equal(a[fixed], b[fixed])  # fixed splats: bit-exact
    # rigidly moved splats keep every log-scale (the thinnest included) to 1e-5
    assert np.abs(g1.scale_log[mov] - g0.scale_log[mov]).max() <= 1e-5
    lin = res.matrix[:3, :3]
    np.testing.assert_allclose(quaternion_to_matrix(g1.rotation[mov]),
                               lin @ quaternion_to_matrix(g0.rotation[mov]), atol=2e-6)
    return lin


def test_tile_sh3_edit_rotates_sh_and_keeps_thin_splats(tile_edit):
    res = tile_edit
    g0, g1 = res.model.gaussians, res.deformed.gaussians
    assert g0.sh_rest.shape[1] == 45
    lin = _check_rigid_and_fixed(res)
    mov = res.deformation.moving_idx
    assert g0.scale_log[mov].min() < -22  # the very thin splats are in the rigid part
    # colour_out(R d) = colour_in(d) on the rigid part, to float32 precision
    rng = np.random.default_rng(21)
    sub = mov[rng.choice(mov.size, 300, replace=False)]
    dirs = unit_dirs(rng, sub.size, 64)
    before = colours(3, g0.sh_dc[sub], g0.sh_rest[sub], dirs)
    after = colours(3, g1.sh_dc[sub], g1.sh_rest[sub], dirs @ lin.T)
    scale = np.linalg.norm(g0.sh_rest[sub].reshape(-1, 3, 15), axis=2)[:, None, :]
    assert (np.abs(after - before) <= 4 * F32 * scale + 1e-9).all()
    assert np.abs(g1.sh_rest[sub] - g0.sh_rest[sub]).max() > 1e-3  # not a copy


def test_tile_bent_region_sh_is_rotation_by_polar_factor(tile_edit):
    res = tile_edit
    g0, g1 = res.model.gaussians, res.deformed.gaussians
    free = res.deformation.free_idx
    jac = _free_jacobians(res)
    upright = np.flatnonzero(np.linalg.det(jac) > 0)  # the flat tile's field folds in places
    free, jac = free[upright], jac[upright]
    polar = np.stack([scipy.linalg.polar(j)[0] for j in jac])
    angle = np.degrees(Rotation.from_matrix(polar).magnitude())
    bent = np.flatnonzero(angle > 5)
    assert bent.size > 50
    pick = bent[:: max(1, bent.size // 150)]
    want = oracle_rotate(g0.sh_rest[free[pick]], polar[pick], 3)
    np.testing.assert_allclose(g1.sh_rest[free[pick]], want,
                               atol=4 * F32 * np.abs(g0.sh_rest[free[pick]]).max())


@pytest.mark.parametrize("which", ["tile", "guitar"])
def test_bent_region_reproduces_jsjt(which, request):
    res = request.getfixturevalue(f"{which}_edit")
    if which == "guitar":
        _check_rigid_and_fixed(res)
    g0, g1 = res.model.gaussians, res.deformed.gaussians
    free = res.deformation.free_idx
    jac = _free_jacobians(res)
    s64 = g0.scale_log[free].astype(np.float64)
    q64 = g0.rotation[free].astype(np.float64)
    # the algorithm in float64: J Sigma J^T to 1e-6 relative ...
    new = deform_gaussians(s64, q64, None, jac, covariance="jacobian")
    want = jac @ covariance(s64, q64) @ jac.transpose(0, 2, 1)
    got = covariance(new.scale_log, new.rotation)
    rel = np.linalg.norm(got - want, axis=(1, 2)) / np.linalg.norm(want, axis=(1, 2))
    assert rel.max() < 1e-6, rel.max()
    # ... and the pipeline stored exactly that, rounded to the file's float32
    np.testing.assert_array_equal(g1.scale_log[free], new.scale_log.astype(np.float32))
    np.testing.assert_array_equal(g1.rotation[free], new.rotation.astype(np.float32))
    # no axis lost: sum of log-scales moves by log |det J| (float32 storage: 1e-5)
    log_det = g1.scale_log[free].astype(np.float64).sum(1) - s64.sum(1)
    np.testing.assert_allclose(log_det, np.log(np.abs(np.linalg.det(jac))), atol=1e-5)


@pytest.mark.parametrize("which", ["tile", "guitar"])
def test_deformed_3dgs_round_trip(which, request):
    res = request.getfixturevalue(f"{which}_edit")
    back = sd.load(res.output)
    assert back.kind == "gaussians" and back.n_points == res.model.n_points
    g, b = res.deformed.gaussians, back.gaussians
    for name in ("scale_log", "rotation", "opacity", "sh_dc", "sh_rest"):
        want = getattr(g, name)
        assert (want is None) == (getattr(b, name) is None), name
        if want is not None:
            np.testing.assert_array_equal(getattr(b, name), want, err_msg=name)
    # the untouched rows of the file are byte-identical, and the header is the input's
    src = res.model.source.element("vertex")
    out = back.source.element("vertex")
    assert [p.name for p in src.properties] == [p.name for p in out.properties]
    fixed = res.deformation.fixed
    assert src.data[fixed].tobytes() == out.data[fixed].tobytes()


def test_zero_edit_leaves_every_splat_bit_exact(tile_edit):
    res = tile_edit
    same = sd.apply(res.deformation, res.model, np.zeros_like(res.delta_c))
    g0, g1 = res.model.gaussians, same.gaussians
    for name in ("scale_log", "rotation", "sh_rest"):
        assert np.array_equal(getattr(g0, name), getattr(g1, name)), name
