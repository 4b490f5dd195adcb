"""The surfel and point-cloud pipeline: two-pass surface splatting -- a depth pre-pass of the
elliptical discs pushed back by ``SURFEL_DEPTH_OFFSET`` splat radii, then Gaussian-weighted
accumulation of colour and normal of every disc within that offset of the front surface (float
targets, additive blending), normalised and shaded in a full-screen pass
(``shaders/surfel_*``). ``blend=False`` draws opaque, depth-tested discs instead."""

from __future__ import annotations

from typing import Any

import numpy as np

from splatdeform.render.gpu import GpuModel, Upload, set_uniforms, surface_vertices
from splatdeform.render.splats import SplatGeometry
from splatdeform.render.targets import Targets

SURFEL_DEPTH_OFFSET = 1.0  # depth pre-pass pushed back by this many splat radii
SURFEL_SCALE = 1.25  # surface splatting enlarges the discs so that neighbours overlap
PREFIXES = ("splat", "surfeldepth", "surfelaccum", "feedback")


def upload(ctx: Any, positions: np.ndarray, geom: SplatGeometry, buffers: list[Any]) -> Upload:
    """Positions (N, 3) float32 (origin-relative) with the discs of ``geom``."""
    content = surface_vertices(ctx, positions, geom.normals, geom.axes, geom.colors, buffers)
    return Upload("splat", content, PREFIXES)


def draw(targets: Targets, gpu: GpuModel, view: np.ndarray, proj: np.ndarray, mode: str,
         delta_c: np.ndarray | None, *, blend: bool = True) -> np.ndarray:
    """(H, W, 4) uint8: surface splatting (``blend``) or opaque discs."""
    if not blend:
        vao = gpu.vaos[f"splat_{mode}"]
        set_uniforms(vao.program, gpu, view, proj, mode, delta_c, depth_offset=0.0)
        return targets.draw_opaque(vao, targets.ctx.POINTS, gpu.n_points)
    ctx = targets.ctx
    t = targets.floats()
    ctx.disable(ctx.CULL_FACE | ctx.BLEND)
    ctx.enable(ctx.DEPTH_TEST)
    t["accum"].use()
    ctx.viewport = (0, 0, *targets.size)
    t["accum"].clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
    # pass 1: depth of the discs pushed back by SURFEL_DEPTH_OFFSET radii
    vao = gpu.vaos[f"surfeldepth_{mode}"]
    set_uniforms(vao.program, gpu, view, proj, mode, delta_c, SURFEL_DEPTH_OFFSET, SURFEL_SCALE)
    t["depth_only"].use()
    ctx.depth_func = "<"
    vao.render(mode=ctx.POINTS, vertices=gpu.n_points)
    # pass 2: weighted colour and normal of every disc in front of that depth
    vao = gpu.vaos[f"surfelaccum_{mode}"]
    set_uniforms(vao.program, gpu, view, proj, mode, delta_c, 0.0, SURFEL_SCALE)
    t["accum"].use()
    t["accum"].depth_mask = False
    ctx.depth_func = "<="
    ctx.enable(ctx.BLEND)
    ctx.blend_func = ctx.ONE, ctx.ONE
    try:
        vao.render(mode=ctx.POINTS, vertices=gpu.n_points)
    finally:
        t["accum"].depth_mask = True
        ctx.depth_func = "<"
        ctx.disable(ctx.BLEND | ctx.DEPTH_TEST)
    # pass 3: normalise and shade
    prog = t["resolve"].program
    t["color"].use(location=0)
    t["normal"].use(location=1)
    t["depth"].use(location=2)
    prog["u_color"].value = 0
    prog["u_normal"].value = 1
    prog["u_depth"].value = 2
    near, far = proj[2, 3] / (proj[2, 2] - 1.0), proj[2, 3] / (proj[2, 2] + 1.0)
    prog["u_near_far"].value = (float(near), float(far))
    prog["u_viewport"].value = tuple(float(s) for s in targets.size)
    prog["u_proj_scale"].value = (float(proj[0, 0]), float(proj[1, 1]))
    prog["u_background"].value = targets.background
    targets.resolved.use()
    ctx.viewport = (0, 0, *targets.size)
    t["resolve"].render(mode=ctx.TRIANGLES, vertices=3)
    return targets.read_resolved()
