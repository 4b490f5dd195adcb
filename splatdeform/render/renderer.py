"""Offscreen splat/mesh rendering with the deforming vertex stage (moderngl, headless EGL).

One :class:`Renderer` owns a multisampled framebuffer of one size. :meth:`Renderer.upload`
sends a model (positions, normals, tangent axes, colors, optional faces) and optionally its
deformation basis ONCE; :meth:`Renderer.draw` then renders it for any delta C with only a
12-float uniform changing per frame. Without a basis (or with ``plain=True``) the plain
program renders the stored geometry (the comparison path for CPU-deformed models).

Basis layout on the GPU: for k <= 4, 16 float32 per point as vertex attributes, values
b_0..b_3 then gradients grad b_0 .. grad b_3; k < 4 is zero-padded. For 4 < k <= MAX_STORAGE_K
(curve edits), a shader storage buffer (GL 4.3+) of 4k float32 per point, k values then 3k
gradient components, read by ``gl_VertexID``; delta C is then ``uniform vec3 u_delta[K]`` with
K a compile-time define (one cached program per K). See ``shaders/deform.vert``.

Positions are uploaded relative to an ``origin`` (the bounding-box centre, float64) so that
scans with large coordinate offsets keep float32 precision; the deformation is translation
invariant (p' - p and J do not depend on where the origin is).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from splatdeform.errors import DeviceError
from splatdeform.model import PointModel
from splatdeform.render.camera import Camera, frame_points, gl_bytes
from splatdeform.render.context import get_context
from splatdeform.render.splats import splat_geometry
from splatdeform.resources import resource_path

MAX_K = 4  # the vertex-attribute path
MAX_STORAGE_K = 128  # the storage-buffer path (u_delta[K] must fit the uniform limits)
STORAGE_GL_VERSION = 430
BACKGROUND = (255, 255, 255)
FEEDBACK_VARYINGS = ("v_position", "v_normal", "v_axis_u", "v_axis_v")

_programs: dict[str, Any] = {}


def _shader(name: str) -> str:
    return resource_path("shaders", name).read_text()


def _source(name: str, *, deform: bool | None = None, shading: bool = False, k: int = 0) -> str:
    """Shader source with the host header; ``k > MAX_K`` selects the storage-buffer path
    (GLSL 4.30, ``#define K k``)."""
    storage = bool(deform) and k > MAX_K
    parts = ["#version 430 core\n" if storage else "#version 330 core\n"]
    if deform is not None:
        parts.append(f"#define DEFORM {int(deform)}\n")
    if storage:
        parts.append(f"#define K {int(k)}\n")
    if shading:
        parts.append(_shader("shading.glsl"))
    parts.append(_shader(name))
    return "".join(parts)


def program(name: str, k: int = 0) -> Any:
    """A compiled program by name, cached: ``splat_plain``, ``splat_deform``, ``mesh_plain``,
    ``mesh_deform``, ``feedback_plain``, ``feedback_deform`` (vertex stage only, with the
    deformed position, normal and axes captured by transform feedback).

    k: basis columns of a ``*_deform`` program; k > 4 compiles the storage-buffer variant
    (cached per k), k <= 4 the attribute variant."""
    ctx = get_context()
    kind, mode = name.split("_")
    deform = {"plain": False, "deform": True}[mode]
    k = int(k) if deform and int(k) > MAX_K else 0
    key = f"{name}:{k}" if k else name
    if key not in _programs:
        if k and ctx.version_code < STORAGE_GL_VERSION:
            raise DeviceError(
                f"render: k = {k} control DOFs need shader storage buffers (OpenGL 4.3), this "
                f"context is OpenGL {ctx.version_code // 100}.{ctx.version_code // 10 % 10}"
            )
        vert = _source("deform.vert", deform=deform, k=k)
        if kind == "splat":
            prog = ctx.program(
                vertex_shader=vert,
                geometry_shader=_source("splat.geom"),
                fragment_shader=_source("splat.frag", shading=True),
            )
        elif kind == "mesh":
            prog = ctx.program(
                vertex_shader=vert, fragment_shader=_source("mesh.frag", shading=True)
            )
        elif kind == "feedback":
            prog = ctx.program(vertex_shader=vert, varyings=list(FEEDBACK_VARYINGS))
        else:  # pragma: no cover - internal names only
            raise ValueError(f"program: unknown name {name!r}")
        _programs[key] = prog
    return _programs[key]


def pack_basis(values: np.ndarray, gradients: np.ndarray, n_points: int) -> np.ndarray:
    """(N, 16) float32: values (N, k) then gradients (N, k, 3), k <= 4 zero-padded to 4."""
    vals = np.asarray(values)
    grads = np.asarray(gradients)
    if vals.ndim != 2 or vals.shape[0] != n_points:
        raise ValueError(f"values: expected shape ({n_points}, k), got {vals.shape}")
    k = vals.shape[1]
    if not 1 <= k <= MAX_K:
        raise ValueError(
            f"values: the attribute path renders k <= {MAX_K} control DOFs, got k = {k} "
            "(larger k needs the storage-buffer path, see shaders/deform.vert)"
        )
    if grads.shape != (n_points, k, 3):
        raise ValueError(f"gradients: expected shape ({n_points}, {k}, 3), got {grads.shape}")
    packed = np.zeros((n_points, 16), dtype=np.float32)
    packed[:, :k] = vals
    packed[:, 4 : 4 + 3 * k] = grads.reshape(n_points, 3 * k)
    return packed


def pack_basis_storage(values: np.ndarray, gradients: np.ndarray, n_points: int) -> np.ndarray:
    """(N, 4k) float32 for the storage-buffer path: per point the k values, then the 3k
    gradient components (grad b_0, grad b_1, ...). Any 1 <= k <= MAX_STORAGE_K."""
    vals = np.asarray(values)
    grads = np.asarray(gradients)
    if vals.ndim != 2 or vals.shape[0] != n_points:
        raise ValueError(f"values: expected shape ({n_points}, k), got {vals.shape}")
    k = vals.shape[1]
    if not 1 <= k <= MAX_STORAGE_K:
        raise ValueError(f"values: expected 1 <= k <= {MAX_STORAGE_K} control DOFs, got k = {k}")
    if grads.shape != (n_points, k, 3):
        raise ValueError(f"gradients: expected shape ({n_points}, {k}, 3), got {grads.shape}")
    packed = np.empty((n_points, 4 * k), dtype=np.float32)
    packed[:, :k] = vals
    packed[:, k:] = grads.reshape(n_points, 3 * k)
    return packed


def pad_delta(delta_c: np.ndarray | None, k: int) -> np.ndarray:
    """(max(k, 4), 3) float32 delta C for the shader: ``delta_c`` (k, 3), zero-padded to 4 rows
    for the attribute path (k <= 4); None -> zeros."""
    out = np.zeros((max(int(k), MAX_K), 3), dtype=np.float32)
    if delta_c is None:
        return out
    d = np.asarray(delta_c, dtype=np.float64)
    if d.shape != (k, 3):
        raise ValueError(f"delta_c: expected shape ({k}, 3) for a {k}-column basis, got {d.shape}")
    out[:k] = d
    return out


@dataclass
class GpuModel:
    """A model resident on the GPU (see :meth:`Renderer.upload`).

    origin: (3,) float64 subtracted from positions before upload. k: basis columns (0: none).
    kind: "splat" (points expanded to ellipses) or "mesh" (indexed triangles).
    lo, hi: (3,) float64 bounding box of the undeformed positions. n_points, n_faces: counts.
    storage: the basis storage buffer (k > 4; bound to binding 0 for each deforming draw).
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

    def bind_storage(self) -> None:
        if self.storage is not None:
            self.storage.bind_to_storage_buffer(binding=0)

    def release(self) -> None:
        for vao in self.vaos.values():
            vao.release()
        for buf in self.buffers:
            buf.release()
        self.vaos.clear()
        self.buffers.clear()
        self.storage = None


class Renderer:
    """Offscreen renderer of one image size (W, H) with ``samples``-fold multisampling."""

    def __init__(
        self,
        size: tuple[int, int] = (256, 256),
        *,
        samples: int = 4,
        background: tuple[int, int, int] = BACKGROUND,
    ) -> None:
        width, height = (int(s) for s in size)
        if width < 1 or height < 1:
            raise ValueError(f"size: expected (width, height) >= 1, got {size}")
        self.ctx = get_context()
        self.size = (width, height)
        self.background = tuple(c / 255.0 for c in background)
        samples = min(int(samples), int(self.ctx.max_samples))
        ctx = self.ctx
        self._ms = ctx.framebuffer(
            color_attachments=[ctx.renderbuffer(self.size, 4, samples=samples)],
            depth_attachment=ctx.depth_renderbuffer(self.size, samples=samples),
        )
        self._resolved = ctx.framebuffer(color_attachments=[ctx.renderbuffer(self.size, 4)])

    # -- upload -------------------------------------------------------------------------------
    def upload(
        self,
        model: PointModel,
        values: np.ndarray | None = None,
        gradients: np.ndarray | None = None,
        *,
        fill_holes: bool = True,
    ) -> GpuModel:
        """Send ``model`` and (optionally) its basis to the GPU once.

        values: (N, k) and gradients: (N, k, 3) float32, both or neither. k <= 4 goes into
        vertex attributes, 4 < k <= MAX_STORAGE_K into a shader storage buffer (GL 4.3+).
        fill_holes: enlarge stored surfels smaller than the sample spacing
        (:func:`splatdeform.render.splats.splat_geometry`); False renders stored axes as they are.
        """
        if (values is None) != (gradients is None):
            raise ValueError("values, gradients: expected both or neither")
        ctx = self.ctx
        n = model.n_points
        if n == 0:
            raise ValueError("model: expected at least one point, got an empty model")
        geom = splat_geometry(model, fill_holes=fill_holes)
        lo, hi = model.bbox()
        origin = (lo + hi) / 2.0
        attrs = np.zeros((n, 12), dtype=np.float32)
        attrs[:, 0:3] = model.positions - origin
        attrs[:, 3:6] = geom.normals
        if geom.axes is not None:
            attrs[:, 6:12] = geom.axes.reshape(n, 6)
        colors = np.zeros((n, 4), dtype=np.uint8)
        colors[:, :3] = geom.colors
        buffers = [ctx.buffer(attrs.tobytes()), ctx.buffer(colors.tobytes())]
        content = [
            (buffers[0], "3f 3f 3f 3f", "in_position", "in_normal", "in_axis_u", "in_axis_v"),
            (buffers[1], "3f1 1x", "in_color"),
        ]
        k = 0
        basis: tuple[Any, ...] | None = None
        storage = None
        if values is not None:
            k = int(np.asarray(values).shape[1]) if np.ndim(values) == 2 else 0
            if k > MAX_K:
                packed = pack_basis_storage(values, gradients, n)
                program("feedback_deform", k)  # compile early: DeviceError below GL 4.3
                storage = ctx.buffer(packed.tobytes())
                buffers.append(storage)
            else:
                packed = pack_basis(values, gradients, n)
                k = int(np.asarray(values).shape[1])
                buffers.append(ctx.buffer(packed.tobytes()))
                basis = (
                    buffers[2],
                    "4f 3f 3f 3f 3f",
                    "in_basis",
                    "in_grad0",
                    "in_grad1",
                    "in_grad2",
                    "in_grad3",
                )
        index = None
        n_faces = 0
        if geom.axes is None:
            faces = np.ascontiguousarray(model.faces, dtype=np.int32)
            n_faces = int(faces.shape[0])
            index = ctx.buffer(faces.tobytes())
            buffers.append(index)
        kind = "splat" if geom.axes is not None else "mesh"
        vaos: dict[str, Any] = {}
        modes = ["plain"] + (["deform"] if k else [])
        for mode in modes:
            full = content + ([basis] if mode == "deform" and basis is not None else [])
            for prefix in (kind, "feedback"):
                vaos[f"{prefix}_{mode}"] = ctx.vertex_array(
                    program(f"{prefix}_{mode}", k),
                    full,
                    index_buffer=index if prefix == "mesh" else None,
                    index_element_size=4,
                    skip_errors=True,
                )
        return GpuModel(origin, k, lo, hi, n, n_faces, kind, buffers, vaos, storage)

    # -- draw ---------------------------------------------------------------------------------
    def draw_rgba(
        self,
        gpu: GpuModel,
        camera: Camera | None = None,
        delta_c: np.ndarray | None = None,
        *,
        plain: bool = False,
    ) -> np.ndarray:
        """Render ``gpu`` deformed by ``delta_c`` (k, 3) (None: undeformed). Returns (H, W, 4)
        uint8, top row first; alpha is the coverage (0 where only background)."""
        ctx = self.ctx
        if camera is None:
            camera = frame_points([np.stack([gpu.lo, gpu.hi])], aspect=self.size[0] / self.size[1])
        if not gpu.k and not plain and delta_c is not None and np.any(delta_c):
            raise ValueError("delta_c: this model was uploaded without a basis (values/gradients)")
        mode = "deform" if (gpu.k and not plain) else "plain"
        vao = gpu.vaos[f"{gpu.kind}_{mode}"]
        prog = vao.program
        prog["u_view"].write(gl_bytes(camera.view(gpu.origin)))
        prog["u_proj"].write(gl_bytes(camera.projection(self.size[0] / self.size[1])))
        if mode == "deform":
            prog["u_delta"].write(pad_delta(delta_c, gpu.k).tobytes())
            gpu.bind_storage()
        self._ms.use()
        ctx.viewport = (0, 0, *self.size)
        self._ms.clear(*self.background, 0.0, depth=1.0)
        ctx.enable(ctx.DEPTH_TEST)
        ctx.disable(ctx.CULL_FACE | ctx.BLEND)
        if gpu.kind == "mesh":
            vao.render(mode=ctx.TRIANGLES)
        else:
            vao.render(mode=ctx.POINTS, vertices=gpu.n_points)
        ctx.copy_framebuffer(self._resolved, self._ms)
        data = self._resolved.read(components=4, alignment=1)
        image = np.frombuffer(data, dtype=np.uint8).reshape(self.size[1], self.size[0], 4)
        return np.ascontiguousarray(image[::-1])

    def draw(
        self,
        gpu: GpuModel,
        camera: Camera | None = None,
        delta_c: np.ndarray | None = None,
        *,
        plain: bool = False,
    ) -> np.ndarray:
        """Like :meth:`draw_rgba`, returning the (H, W, 3) uint8 RGB image."""
        return np.ascontiguousarray(self.draw_rgba(gpu, camera, delta_c, plain=plain)[:, :, :3])

    # -- read-back of the vertex stage ----------------------------------------------------------
    def transform(self, gpu: GpuModel, delta_c: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Run only the vertex stage (transform feedback) and read its outputs back.

        Returns positions (N, 3) float64 (origin added back), normals (N, 3) float32 and
        axes (N, 2, 3) float32: exactly what the rasteriser receives.
        """
        mode = "deform" if gpu.k else "plain"
        vao = gpu.vaos[f"feedback_{mode}"]
        prog = vao.program
        eye = gl_bytes(np.eye(4))
        prog["u_view"].write(eye)
        prog["u_proj"].write(eye)
        if mode == "deform":
            prog["u_delta"].write(pad_delta(delta_c, gpu.k).tobytes())
            gpu.bind_storage()
        out = self.ctx.buffer(reserve=gpu.n_points * 12 * 4)
        self._ms.use()  # a surfaceless EGL context has no default framebuffer: draws need one
        try:
            vao.transform(out, mode=self.ctx.POINTS, vertices=gpu.n_points)
            data = np.frombuffer(out.read(), dtype=np.float32).reshape(gpu.n_points, 12)
        finally:
            out.release()
        return {
            "positions": data[:, 0:3].astype(np.float64) + gpu.origin,
            "normals": data[:, 3:6].copy(),
            "axes": data[:, 6:12].reshape(gpu.n_points, 2, 3).copy(),
        }

    def release(self) -> None:
        self._ms.release()
        self._resolved.release()


def save_png(image: np.ndarray, path: str | os.PathLike[str]) -> Path:
    """Write an (H, W, 3|4) uint8 image as PNG atomically (temp file in the folder, then
    os.replace). Returns the path."""
    from PIL import Image

    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise ValueError(f"image: expected (H, W, 3|4) uint8, got {arr.shape} {arr.dtype}")
    return save_pil(Image.fromarray(arr), path, format="PNG")


def save_pil(image: Any, path: str | os.PathLike[str], **save_kwargs: Any) -> Path:
    """Save a Pillow image atomically, mode 0644 like models (the tool's one atomic writer,
    :func:`splatdeform.io.atomic.atomic_write`: temp file in the target folder, then rename)."""
    from splatdeform.io.atomic import atomic_write

    out = Path(path)
    with atomic_write(out) as handle:
        image.save(handle, **save_kwargs)
    return out


def deformed_positions(
    model: PointModel, values: np.ndarray | None, delta_c: np.ndarray | None
) -> np.ndarray:
    """(N, 3) float64 positions after ``delta_c`` (CPU, for camera framing only)."""
    if values is None or delta_c is None:
        return model.positions
    from splatdeform.frame import displace

    return displace(model.positions, np.asarray(values, dtype=np.float64), delta_c)


@contextlib.contextmanager
def deformation_session(
    model: PointModel,
    values: np.ndarray | None,
    gradients: np.ndarray | None,
    delta_c: np.ndarray | None,
    *,
    size: tuple[int, int],
    azimuth: float,
    elevation: float,
    fov: float,
    camera: Camera | None = None,
) -> Iterator[tuple[Renderer, GpuModel, Camera]]:
    """Upload ``model`` with its basis (values (N, k), gradients (N, k, 3), or None) once,
    frame a camera on the undeformed and the ``delta_c`` (k, 3)-deformed positions (unless
    ``camera`` is given), and release the GL objects on exit. Yields (renderer, gpu, camera)."""
    renderer = Renderer(size)
    gpu = renderer.upload(model, values, gradients)
    try:
        if camera is None:
            camera = frame_points(
                [model.positions, deformed_positions(model, values, delta_c)],
                azimuth=azimuth,
                elevation=elevation,
                fov=fov,
                aspect=renderer.size[0] / renderer.size[1],
            )
        yield renderer, gpu, camera
    finally:
        gpu.release()
        renderer.release()


def render_image(
    model: PointModel,
    *,
    values: np.ndarray | None = None,
    gradients: np.ndarray | None = None,
    delta_c: np.ndarray | None = None,
    camera: Camera | None = None,
    size: tuple[int, int] = (256, 256),
    azimuth: float = 30.0,
    elevation: float = 20.0,
    fov: float = 35.0,
) -> np.ndarray:
    """Render ``model`` (deformed on the GPU by ``delta_c`` (k, 3) when the basis ``values``
    (N, k) / ``gradients`` (N, k, 3) are given) to an (H, W, 3) uint8 image.

    camera: None frames the union of the bounding boxes before and after the deformation
    from ``azimuth`` / ``elevation`` / ``fov`` (degrees).
    """
    with deformation_session(model, values, gradients, delta_c, size=size, azimuth=azimuth,
                             elevation=elevation, fov=fov, camera=camera) as (renderer, gpu, cam):
        return renderer.draw(gpu, cam, delta_c)
