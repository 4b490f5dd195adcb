"""A model resident on the GPU and the uniforms every pipeline sets per draw."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from splatdeform.render.camera import gl_bytes
from splatdeform.render.packing import pad_delta


@dataclass
class GpuModel:
    """A model resident on the GPU (see :meth:`splatdeform.render.Renderer.upload`).

    origin: (3,) float64 subtracted from positions before upload. k: basis columns (0: none).
    kind: "splat" (surfels / points expanded to ellipses), "mesh" (indexed triangles) or
    "gaussian" (3D Gaussian splats). lo, hi: (3,) float64 bounding box of the undeformed
    positions. n_points, n_faces: counts. storage: the basis storage buffer (k > 4; bound to
    binding 0 for each deforming draw). For Gaussians: ``positions`` (N, 3) float32 and
    ``values`` (N, k) float32 stay on the host for the per-frame depth sort, ``order`` is the
    index buffer the sorted order is written to, ``sh_buffer`` the SH bands (binding 1).
    """

    origin: np.ndarray
    k: int
    lo: np.ndarray
    hi: np.ndarray
    n_points: int
    n_faces: int
    kind: str
    buffers: list[Any]
    vaos: dict[str, Any]
    storage: Any = None
    positions: np.ndarray | None = None
    values: np.ndarray | None = None
    order: Any = None
    sh_buffer: Any = None
    sh: tuple[int, int] = (0, 0)
    timings: dict[str, float] = field(default_factory=dict)

    def bind_storage(self) -> None:
        if self.storage is not None:
            self.storage.bind_to_storage_buffer(binding=0)
        if self.sh_buffer is not None:
            self.sh_buffer.bind_to_storage_buffer(binding=1)

    def release(self) -> None:
        for vao in self.vaos.values():
            vao.release()
        for buf in self.buffers:
            buf.release()
        self.vaos.clear()
        self.buffers.clear()
        self.storage = None
        self.order = None
        self.sh_buffer = None


@dataclass
class Upload:
    """What a pipeline sends for one model besides the basis: the vertex-array ``content``
    (moderngl's (buffer, layout, names...) entries), the program ``prefixes`` it draws with,
    its ``index`` buffer (or None), ``n_faces`` and the extra :class:`GpuModel` fields;
    ``host_values``: the basis values stay on the host too (the Gaussians' depth sort)."""

    kind: str
    content: list[tuple[Any, ...]]
    prefixes: tuple[str, ...]
    index: Any = None
    n_faces: int = 0
    extra: dict[str, Any] = field(default_factory=dict)
    host_values: bool = False


def set_uniforms(prog: Any, gpu: GpuModel, view: np.ndarray, proj: np.ndarray, mode: str,
                 delta_c: np.ndarray | None, depth_offset: float | None = None,
                 splat_scale: float | None = None) -> None:
    """The (4, 4) ``view`` and ``proj`` matrices; the surfel depth offset and splat scale where
    the program has them (``depth_offset`` not None); delta C (k, 3) and the storage buffers
    for a ``deform`` draw."""
    prog["u_view"].write(gl_bytes(view))
    prog["u_proj"].write(gl_bytes(proj))
    if depth_offset is not None and "u_depth_offset" in prog:
        prog["u_depth_offset"].value = float(depth_offset)
        prog["u_splat_scale"].value = 1.0 if splat_scale is None else float(splat_scale)
    if mode == "deform":
        prog["u_delta"].write(pad_delta(delta_c, gpu.k).tobytes())
        gpu.bind_storage()


def surface_vertices(ctx: Any, positions: np.ndarray, normals: np.ndarray,
                     axes: np.ndarray | None, colors: np.ndarray,
                     buffers: list[Any]) -> list[tuple[Any, ...]]:
    """The vertex layout of ``deform.vert`` (surfels and meshes): (N, 3) float32 positions,
    normals (N, 3), tangent axes (N, 2, 3) or None (zeros), (N, 3) uint8 colours. The new
    buffers are appended to ``buffers``; returns the vertex-array content."""
    n = positions.shape[0]
    attrs = np.zeros((n, 12), dtype=np.float32)
    attrs[:, 0:3] = positions
    attrs[:, 3:6] = normals
    if axes is not None:
        attrs[:, 6:12] = axes.reshape(n, 6)
    rgba = np.zeros((n, 4), dtype=np.uint8)
    rgba[:, :3] = colors
    buffers += [ctx.buffer(attrs.tobytes()), ctx.buffer(rgba.tobytes())]
    return [
        (buffers[-2], "3f 3f 3f 3f", "in_position", "in_normal", "in_axis_u", "in_axis_v"),
        (buffers[-1], "3f1 1x", "in_color"),
    ]
