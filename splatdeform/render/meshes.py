"""The mesh pipeline: indexed triangles, depth-tested, multisampled."""

from __future__ import annotations

from typing import Any

import numpy as np

from splatdeform.model import PointModel
from splatdeform.render.gpu import GpuModel, Upload, set_uniforms, surface_vertices
from splatdeform.render.splats import SplatGeometry
from splatdeform.render.targets import Targets

PREFIXES = ("mesh", "feedback")


def upload(ctx: Any, model: PointModel, positions: np.ndarray, geom: SplatGeometry,
           buffers: list[Any]) -> Upload:
    """Positions (N, 3) float32 (origin-relative), ``geom``'s normals and colours, and the
    model's (F, 3) faces as the index buffer."""
    content = surface_vertices(ctx, positions, geom.normals, None, geom.colors, buffers)
    faces = np.ascontiguousarray(model.faces, dtype=np.int32)
    buffers.append(ctx.buffer(faces.tobytes()))
    return Upload("mesh", content, PREFIXES, index=buffers[-1], n_faces=int(faces.shape[0]))


def draw(targets: Targets, gpu: GpuModel, view: np.ndarray, proj: np.ndarray, mode: str,
         delta_c: np.ndarray | None) -> np.ndarray:
    """(H, W, 4) uint8 of the triangles."""
    vao = gpu.vaos[f"mesh_{mode}"]
    set_uniforms(vao.program, gpu, view, proj, mode, delta_c, depth_offset=0.0)
    return targets.draw_opaque(vao, targets.ctx.TRIANGLES)
