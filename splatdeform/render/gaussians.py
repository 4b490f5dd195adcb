"""The 3D Gaussian splat pipeline: EWA splatting as in 3DGS -- each Gaussian's deformed
covariance J Sigma J^T is projected to a 2D conic (plus the 0.3 px low-pass), its opacity is
sigmoid(logit), its colour the SH expansion (degree <= 3) in the view direction; splats are
sorted back to front by view depth on the CPU each frame (numpy argsort of the deformed depths)
and composited with premultiplied alpha into a float target (``shaders/gauss.*``). Higher SH
bands come from a storage buffer (GL 4.3+)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from splatdeform.model import PointModel
from splatdeform.render.camera import Camera
from splatdeform.render.gaussian_data import gaussian_data
from splatdeform.render.gpu import GpuModel, Upload, set_uniforms
from splatdeform.render.targets import Targets

PREFIXES = ("gauss", "feedback")


def upload(ctx: Any, model: PointModel, positions: np.ndarray, buffers: list[Any]) -> Upload:
    """Positions (N, 3) float32 (origin-relative) with the fields of :func:`gaussian_data`, an
    index buffer for the per-frame order and the SH bands' storage buffer."""
    gd = gaussian_data(model)
    attrs = np.concatenate([positions, gd.cov, gd.color, gd.shape], axis=1)
    attrs = np.ascontiguousarray(attrs, dtype=np.float32)
    buffers.append(ctx.buffer(attrs.tobytes()))
    content = [(buffers[-1], "3f 3f 3f 4f 2f", "in_position", "in_cov_a", "in_cov_b",
                "in_color", "in_shape")]
    order = ctx.buffer(reserve=model.n_points * 4)
    buffers.append(order)
    extra: dict[str, Any] = {"order": order, "positions": positions, "sh": (gd.degree, gd.rest)}
    if gd.sh_rest is not None:
        extra["sh_buffer"] = ctx.buffer(gd.sh_rest.tobytes())
        buffers.append(extra["sh_buffer"])
    return Upload("gaussian", content, PREFIXES, index=order, extra=extra, host_values=True)


def depth_order(positions: np.ndarray, view: np.ndarray, values: np.ndarray | None = None,
                delta_c: np.ndarray | None = None) -> np.ndarray:
    """(N,) uint32 back-to-front drawing order of (N, 3) positions, deformed by ``values``
    (N, k) and ``delta_c`` (k, 3) when given, under the (4, 4) ``view`` matrix: ascending
    view-space z (the camera looks down -z), ties in index order. Only z is formed:
    z = p . v + b . (delta C v), v the view matrix's third row."""
    v = np.asarray(view[2, :3], dtype=positions.dtype)
    z = positions @ v
    if values is not None and delta_c is not None:
        z += values @ (np.asarray(delta_c, dtype=values.dtype).reshape(values.shape[1], 3) @ v)
    return np.argsort(z, kind="stable").astype(np.uint32)


def composite(targets: Targets, gpu: GpuModel, camera: Camera, view: np.ndarray,
              proj: np.ndarray, mode: str, delta_c: np.ndarray | None) -> np.ndarray:
    """Sort by deformed view depth (CPU), then composite back to front (premultiplied).
    Returns the (H, W, 4) float32 composite (rgb over the background, alpha = 1 -
    transmittance), top row first; ``gpu.timings`` gets ``sort`` and ``frame`` seconds."""
    ctx = targets.ctx
    t0 = time.perf_counter()
    deformed = mode == "deform" and delta_c is not None and gpu.values is not None
    order = depth_order(gpu.positions, view, gpu.values if deformed else None,
                        delta_c if deformed else None)
    gpu.order.write(order.tobytes())
    gpu.timings["sort"] = time.perf_counter() - t0
    vao = gpu.vaos[f"gauss_{mode}"]
    prog = vao.program
    set_uniforms(prog, gpu, view, proj, mode, delta_c)
    values = {"u_viewport": tuple(float(s) for s in targets.size),
              "u_eye": tuple(float(v) for v in camera.eye() - gpu.origin),
              "u_near": float(camera.near)}
    for name, value in values.items():
        if name in prog:  # unused uniforms are compiled away (u_eye without SH bands)
            prog[name].value = value
    gpu.bind_storage()
    t = targets.floats()
    t["gauss"].use()
    ctx.viewport = (0, 0, *targets.size)
    t["gauss"].clear(*targets.background, 0.0)
    ctx.disable(ctx.DEPTH_TEST | ctx.CULL_FACE)
    ctx.enable(ctx.BLEND)
    ctx.blend_func = ctx.ONE, ctx.ONE_MINUS_SRC_ALPHA
    try:
        vao.render(mode=ctx.POINTS, vertices=gpu.n_points)
    finally:
        ctx.disable(ctx.BLEND)
    image = targets.read_float()
    gpu.timings["frame"] = time.perf_counter() - t0
    return image


def draw(targets: Targets, gpu: GpuModel, camera: Camera, view: np.ndarray, proj: np.ndarray,
         mode: str, delta_c: np.ndarray | None) -> np.ndarray:
    """(H, W, 4) uint8 of :func:`composite` (alpha: the accumulated opacity)."""
    image = composite(targets, gpu, camera, view, proj, mode, delta_c)
    return np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)
