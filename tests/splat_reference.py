"""A numpy reference rasteriser of 3D Gaussian splats: the oracle of the GL renderer.

Brute force, float64, written from the 3DGS conventions (not from the shaders): per splat in
back-to-front order, every pixel centre of its 3-sigma box gets
alpha = min(0.99, sigmoid(opacity) * exp(-0.5 d^T conic d)) (dropped below 1/255) and is
composited with "over". The 2D covariance is the EWA projection J_p W Sigma' W^T J_p^T + 0.3 I
(x/z clamped to 1.3 tan(fov/2) in J_p, as 3DGS); Sigma' = J Sigma J^T for a deformed splat;
colour = max(0, 0.5 + SH(d)) with d the unit direction from the eye to the mean, rotated by R^T
(R: rotation of the polar decomposition of J, from an SVD) for a deformed splat.
"""

from __future__ import annotations

import numpy as np

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def rotation_matrices(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions w, x, y, z -> (N, 3, 3)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], axis=1).reshape(-1, 3, 3)


def sh_basis(d: np.ndarray, degree: int) -> np.ndarray:
    """(N, (degree+1)^2) real SH basis values (3DGS sign conventions) at unit directions d."""
    x, y, z = d.T
    cols = [np.full_like(x, C0)]
    if degree > 0:
        cols += [-C1 * y, C1 * z, -C1 * x]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        cols += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z,
                 C2[4] * (xx - yy)]
    if degree > 2:
        cols += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
                 C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
                 C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    return np.stack(cols, axis=1)


def reference_render(model, camera, size, values=None, gradients=None, delta_c=None,
                     background=(1.0, 1.0, 1.0), rotate_sh=True) -> np.ndarray:
    """(H, W, 4) float64 image (top row first): rgb composited over ``background``, alpha =
    1 - transmittance. ``model`` has 3DGS fields; the optional basis deforms it by delta_c.
    ``rotate_sh=False`` evaluates a deformed splat's SH unrotated (a negative control)."""
    g = model.gaussians
    width, height = size
    p = model.positions.astype(np.float64)
    n = p.shape[0]
    jac = np.broadcast_to(np.eye(3), (n, 3, 3))
    if delta_c is not None and values is not None:
        d = np.asarray(delta_c, dtype=np.float64)
        p = p + values.astype(np.float64) @ d
        jac = np.eye(3) + np.einsum("kc,nkd->ncd", d, gradients.astype(np.float64))
    rot = rotation_matrices(g.rotation.astype(np.float64))
    s2 = np.exp(2 * g.scale_log.astype(np.float64))
    sigma = rot @ (s2[:, :, None] * rot.transpose(0, 2, 1))
    sigma = jac @ sigma @ jac.transpose(0, 2, 1)

    view = camera.view()
    proj = camera.projection(width / height)
    t = p @ view[:3, :3].T + view[:3, 3]
    z = -t[:, 2]
    fx, fy = 0.5 * width * proj[0, 0], 0.5 * height * proj[1, 1]
    limx, limy = 1.3 / proj[0, 0], 1.3 / proj[1, 1]
    zs = np.where(z > 0, z, 1.0)
    tx = np.clip(t[:, 0] / zs, -limx, limx) * zs
    ty = np.clip(t[:, 1] / zs, -limy, limy) * zs
    jp = np.zeros((n, 2, 3))
    jp[:, 0, 0] = fx / zs
    jp[:, 0, 2] = fx * tx / zs**2
    jp[:, 1, 1] = fy / zs
    jp[:, 1, 2] = fy * ty / zs**2
    tm = jp @ view[:3, :3]
    cov = tm @ sigma @ tm.transpose(0, 2, 1)
    a, b, c = cov[:, 0, 0] + 0.3, cov[:, 0, 1], cov[:, 1, 1] + 0.3
    det = a * c - b * b
    valid = (z > camera.near) & (det > 0)
    det = np.where(valid, det, 1.0)
    conic = np.stack([c / det, -b / det, a / det], axis=1)
    center = np.stack([fx * t[:, 0] / zs + width / 2, fy * t[:, 1] / zs + height / 2], axis=1)
    extent = 3 * np.sqrt(np.stack([a, c], axis=1))

    rgb = 0.5 + C0 * g.sh_dc.astype(np.float64)
    if g.sh_rest is not None:
        rest = g.sh_rest.shape[1] // 3
        degree = {3: 1, 8: 2, 15: 3}[rest]
        direction = p - camera.eye()
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        if delta_c is not None and values is not None and rotate_sh:
            u, _, vt = np.linalg.svd(jac)
            polar = u @ vt
            direction = np.einsum("nji,nj->ni", polar, direction)  # R^T d
        basis = sh_basis(direction, degree)[:, 1:]  # (N, rest)
        coeffs = g.sh_rest.astype(np.float64).reshape(n, 3, rest)  # channel-major
        rgb = rgb + np.einsum("nj,ncj->nc", basis, coeffs)
    rgb = np.maximum(rgb, 0.0)
    opacity = 1.0 / (1.0 + np.exp(-g.opacity.astype(np.float64)))

    image = np.empty((height, width, 4))
    image[:, :, :3] = background
    image[:, :, 3] = 0.0
    xs, ys = np.arange(width) + 0.5, np.arange(height) + 0.5
    for i in np.argsort(t[:, 2], kind="stable"):  # back to front
        if not valid[i]:
            continue
        cx, cy = center[i]
        ex, ey = extent[i]
        x0, x1 = np.searchsorted(xs, cx - ex), np.searchsorted(xs, cx + ex, side="right")
        y0, y1 = np.searchsorted(ys, cy - ey), np.searchsorted(ys, cy + ey, side="right")
        if x0 >= x1 or y0 >= y1:
            continue
        dx = xs[x0:x1][None, :] - cx
        dy = ys[y0:y1][:, None] - cy
        ca, cb, cc = conic[i]
        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
        alpha = np.minimum(0.99, opacity[i] * np.exp(power))
        alpha = np.where((power <= 0) & (alpha >= 1 / 255), alpha, 0.0)[:, :, None]
        block = image[y0:y1, x0:x1]
        block[:, :, :3] = rgb[i] * alpha + (1 - alpha) * block[:, :, :3]
        block[:, :, 3:] = alpha + (1 - alpha) * block[:, :, 3:]
    return image[::-1]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two uint8 (or [0, 255] float) images."""
    mse = np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))
