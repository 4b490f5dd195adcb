"""Offscreen rendering with the deforming vertex stage (moderngl, headless EGL).

One :class:`Renderer` owns framebuffers of one size. :meth:`Renderer.upload` sends a model and
optionally its deformation basis ONCE; :meth:`Renderer.draw` then renders it for any delta C with
only a 12-float uniform changing per frame (plus, for Gaussians, the per-frame depth order).
Without a basis (or with ``plain=True``) the plain programs render the stored geometry (the
comparison path for CPU-deformed models). Three kinds of model:

- ``gaussian`` (3D Gaussian splats): EWA splatting as in 3DGS -- each Gaussian's deformed
  covariance J Sigma J^T is projected to a 2D conic (plus the 0.3 px low-pass), its opacity is
  sigmoid(logit), its colour the SH expansion (degree <= 3) in the view direction; splats are
  sorted back to front by view depth on the CPU each frame (numpy argsort of the deformed
  depths) and composited with premultiplied alpha into a float target (``shaders/gauss.*``).
- ``splat`` (surfels and point clouds): two-pass surface splatting -- a depth pre-pass of the
  elliptical discs pushed back by ``SURFEL_DEPTH_OFFSET`` splat radii, then Gaussian-weighted
  accumulation of colour and normal of every disc within that offset of the front surface
  (float targets, additive blending), normalised and shaded in a full-screen pass
  (``shaders/surfel_*``). ``blend=False`` draws opaque, depth-tested discs instead.
- ``mesh``: indexed triangles, depth-tested, 4x multisampled.

Basis layout on the GPU: for k <= 4, 16 float32 per point as vertex attributes, values
b_0..b_3 then gradients grad b_0 .. grad b_3; k < 4 is zero-padded. For 4 < k <= MAX_STORAGE_K
(curve edits), a shader storage buffer (GL 4.3+) of 4k float32 per point, k values then 3k
gradient components, read by ``gl_VertexID``; delta C is then ``uniform vec3 u_delta[K]`` with
K a compile-time define (one cached program per K). See ``shaders/deform.glsl``. Higher SH
bands of Gaussians come from a second storage buffer (GL 4.3+).

Positions are uploaded relative to an ``origin`` (the bounding-box centre, float64) so that
scans with large coordinate offsets keep float32 precision; the deformation is translation
invariant (p' - p and J do not depend on where the origin is).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from splatdeform.deform.gaussians import COVARIANCE_MODES
from splatdeform.errors import DeviceError, InputError
from splatdeform.model import PointModel
from splatdeform.render.camera import Camera, default_up, frame_points, gl_bytes
from splatdeform.render.context import get_context
from splatdeform.render.gaussian_data import gaussian_data
from splatdeform.render.splats import splat_geometry
from splatdeform.resources import resource_path

MAX_K = 4  # the vertex-attribute path
MAX_STORAGE_K = 128  # the storage-buffer path (u_delta[K] must fit the uniform limits)
STORAGE_GL_VERSION = 430
BACKGROUND = (255, 255, 255)
FEEDBACK_VARYINGS = ("v_position", "v_normal", "v_axis_u", "v_axis_v")
SURFEL_DEPTH_OFFSET = 1.0  # depth pre-pass pushed back by this many splat radii
SURFEL_SCALE = 1.25  # surface splatting enlarges the discs so that neighbours overlap

# compiled programs per context (a thread's own context, see render/context.py); a context
# object is kept here with its programs, so its id is never reused while the entry lives
_programs_of: dict[int, tuple[Any, dict[tuple[str, bool, int, int, str], Any]]] = {}


def _shader(name: str) -> str:
    return resource_path("shaders", name).read_text()


def _source(name: str, *, deform: bool | None = None, shading: bool = False, k: int = 0,
            storage: bool = False, sh: tuple[int, int] | None = None,
            covariance: str | None = None) -> str:
    """Shader source with the host header. ``k > MAX_K`` selects the basis storage buffer and
    ``storage`` (SH bands) GLSL 4.30; vertex stages (``deform`` not None) get deform.glsl;
    ``covariance`` (a ``gaussians.covariance`` mode) defines COVARIANCE and adds covariance.glsl."""
    storage = storage or (bool(deform) and k > MAX_K)
    parts = ["#version 430 core\n" if storage else "#version 330 core\n"]
    if deform is not None:
        parts.append(f"#define DEFORM {int(deform)}\n")
        if deform and k > MAX_K:
            parts.append(f"#define K {int(k)}\n")
    if sh is not None:
        parts.append(f"#define SH_DEGREE {int(sh[0])}\n#define SH_REST {int(sh[1])}\n")
    if shading:
        parts.append(_shader("shading.glsl"))
    if covariance is not None:
        parts.append(f"#define COVARIANCE {COVARIANCE_MODES.index(covariance)}\n")
    if deform is not None:
        parts.append(_shader("deform.glsl"))
    if covariance is not None:
        parts.append(_shader("covariance.glsl"))
    parts.append(_shader(name))
    return "".join(parts)


def program(name: str, k: int = 0, sh: tuple[int, int] = (0, 0),
            covariance: str = "jacobian") -> Any:
    """A compiled program by name, cached. Names: ``<kind>_<mode>`` with mode ``plain`` or
    ``deform`` and kind ``splat`` (opaque discs), ``surfeldepth`` / ``surfelaccum`` (surface
    splatting passes 1-2), ``mesh``, ``gauss`` (3DGS), ``feedback`` (vertex stage only, the
    deformed position, normal and axes captured by transform feedback); and ``resolve``
    (surface splatting pass 3).

    k: basis columns of a ``*_deform`` program; k > 4 compiles the storage-buffer variant
    (cached per k), k <= 4 the attribute variant. sh: (degree, coefficients per channel of
    f_rest) of a ``gauss_*`` program; degree > 0 reads them from a storage buffer.
    covariance: the ``gaussians.covariance`` mode of a ``gauss_deform`` program."""
    ctx = get_context()
    if name == "resolve":
        kind, deform = "resolve", False
    else:
        kind, mode = name.split("_")
        deform = {"plain": False, "deform": True}[mode]
    k = int(k) if deform and int(k) > MAX_K else 0
    sh = (int(sh[0]), int(sh[1])) if kind == "gauss" and int(sh[0]) > 0 else (0, 0)
    covariance = covariance if kind == "gauss" and deform else "jacobian"
    key = (kind, deform, k, sh[0] * 1000 + sh[1], covariance)
    _programs = _programs_of.setdefault(id(ctx), (ctx, {}))[1]
    if key not in _programs:
        if (k or sh[0]) and ctx.version_code < STORAGE_GL_VERSION:
            what = f"k = {k} control DOFs" if k else f"SH degree {sh[0]} colours"
            raise DeviceError(
                f"render: {what} need shader storage buffers (OpenGL 4.3), this "
                f"context is OpenGL {ctx.version_code // 100}.{ctx.version_code // 10 % 10}"
            )
        if kind == "resolve":
            prog = ctx.program(vertex_shader=_source("surfel_resolve.vert"),
                               fragment_shader=_source("surfel_resolve.frag", shading=True)
                               + _shader("edl.glsl"))   # eye-dome lighting, declared there
            _programs[key] = prog
            return prog
        if kind == "gauss":
            prog = ctx.program(
                vertex_shader=_source("gauss.vert", deform=deform, k=k, storage=sh[0] > 0, sh=sh,
                                      covariance=covariance),
                geometry_shader=_source("gauss.geom"),
                fragment_shader=_source("gauss.frag"),
            )
            _programs[key] = prog
            return prog
        vert = _source("deform.vert", deform=deform, k=k)
        frag = {"splat": ("splat.frag", True), "surfeldepth": ("surfel_depth.frag", False),
                "surfelaccum": ("surfel_accum.frag", False)}
        if kind in frag:
            prog = ctx.program(
                vertex_shader=vert,
                geometry_shader=_source("splat.geom"),
                fragment_shader=_source(frag[kind][0], shading=frag[kind][1]),
            )
        elif kind == "mesh":
            prog = ctx.program(
                vertex_shader=vert, fragment_shader=_source("mesh.frag", shading=True)
            )
        elif kind == "feedback":
            prog = ctx.program(vertex_shader=vert, varyings=list(FEEDBACK_VARYINGS))
        else:  # pragma: no cover - internal names only
            raise InputError(f"program: unknown name {name!r}")
        _programs[key] = prog
    return _programs[key]


def pack_basis(values: np.ndarray, gradients: np.ndarray, n_points: int) -> np.ndarray:
    """(N, 16) float32: values (N, k) then gradients (N, k, 3), k <= 4 zero-padded to 4."""
    vals = np.asarray(values)
    grads = np.asarray(gradients)
    if vals.ndim != 2 or vals.shape[0] != n_points:
        raise InputError(f"values: expected shape ({n_points}, k), got {vals.shape}")
    k = vals.shape[1]
    if not 1 <= k <= MAX_K:
        raise InputError(
            f"values: the attribute path renders k <= {MAX_K} control DOFs, got k = {k} "
            "(larger k needs the storage-buffer path, see shaders/deform.glsl)"
        )
    if grads.shape != (n_points, k, 3):
        raise InputError(f"gradients: expected shape ({n_points}, {k}, 3), got {grads.shape}")
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
        raise InputError(f"values: expected shape ({n_points}, k), got {vals.shape}")
    k = vals.shape[1]
    if not 1 <= k <= MAX_STORAGE_K:
        raise InputError(f"values: expected 1 <= k <= {MAX_STORAGE_K} control DOFs, got k = {k}")
    if grads.shape != (n_points, k, 3):
        raise InputError(f"gradients: expected shape ({n_points}, {k}, 3), got {grads.shape}")
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
        raise InputError(f"delta_c: expected shape ({k}, 3) for a {k}-column basis, got {d.shape}")
    out[:k] = d
    return out


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


@dataclass
class GpuModel:
    """A model resident on the GPU (see :meth:`Renderer.upload`).

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


class Renderer:
    """Offscreen renderer of one image size (W, H): a ``samples``-fold multisampled target for
    meshes and opaque splats, float targets for blended surfels and Gaussians."""

    def __init__(
        self,
        size: tuple[int, int] = (256, 256),
        *,
        samples: int = 4,
        background: tuple[int, int, int] = BACKGROUND,
    ) -> None:
        width, height = (int(s) for s in size)
        if width < 1 or height < 1:
            raise InputError(f"size: expected (width, height) >= 1, got {size}")
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
        self._float: dict[str, Any] | None = None  # created on first blended draw

    def _float_targets(self) -> dict[str, Any]:
        if self._float is None:
            ctx = self.ctx
            color = ctx.texture(self.size, 4, dtype="f4")
            normal = ctx.texture(self.size, 4, dtype="f4")
            depth = ctx.depth_texture(self.size)
            depth.compare_func = ""  # read as values in the resolve pass
            self._float = {
                "color": color,
                "normal": normal,
                "depth": depth,
                "accum": ctx.framebuffer(color_attachments=[color, normal],
                                         depth_attachment=depth),
                "depth_only": ctx.framebuffer(depth_attachment=depth),
                "gauss": ctx.framebuffer(color_attachments=[color]),
                "resolve": ctx.vertex_array(program("resolve"), []),
            }
        return self._float

    # -- upload -------------------------------------------------------------------------------
    def upload(
        self,
        model: PointModel,
        values: np.ndarray | None = None,
        gradients: np.ndarray | None = None,
        *,
        fill_holes: bool = True,
        covariance: str = "jacobian",
    ) -> GpuModel:
        """Send ``model`` and (optionally) its basis to the GPU once.

        values: (N, k) and gradients: (N, k, 3) float32, both or neither. k <= 4 goes into
        vertex attributes, 4 < k <= MAX_STORAGE_K into a shader storage buffer (GL 4.3+).
        fill_holes: enlarge stored surfels smaller than the sample spacing
        (:func:`splatdeform.render.splats.splat_geometry`); False renders stored axes as they are.
        Models with 3D Gaussian splat fields render as Gaussians, deformed covariances by the
        ``covariance`` mode (:data:`splatdeform.deform.gaussians.COVARIANCE_MODES`).
        """
        if (values is None) != (gradients is None):
            raise InputError("values, gradients: expected both or neither")
        if covariance not in COVARIANCE_MODES:
            raise InputError(f"gaussians.covariance: expected one of "
                             f"{', '.join(COVARIANCE_MODES)}, got {covariance!r}")
        ctx = self.ctx
        n = model.n_points
        if n == 0:
            raise InputError("model: expected at least one point, got an empty model")
        lo, hi = model.bbox()
        origin = (lo + hi) / 2.0
        positions = np.ascontiguousarray(model.positions - origin, dtype=np.float32)
        buffers: list[Any] = []
        extra: dict[str, Any] = {}
        vaos: dict[str, Any] = {}
        try:
            if model.gaussians is not None:
                kind = "gaussian"
                gd = gaussian_data(model)
                attrs = np.concatenate([positions, gd.cov, gd.color, gd.shape], axis=1)
                attrs = np.ascontiguousarray(attrs, dtype=np.float32)
                buffers.append(ctx.buffer(attrs.tobytes()))
                content = [(buffers[0], "3f 3f 3f 4f 2f", "in_position", "in_cov_a",
                            "in_cov_b", "in_color", "in_shape")]
                order = ctx.buffer(reserve=n * 4)
                buffers.append(order)
                extra.update(order=order, positions=positions, sh=(gd.degree, gd.rest))
                if gd.sh_rest is not None:
                    extra["sh_buffer"] = ctx.buffer(gd.sh_rest.tobytes())
                    buffers.append(extra["sh_buffer"])
                prefixes = ("gauss", "feedback")
            else:
                geom = splat_geometry(model, fill_holes=fill_holes)
                kind = "splat" if geom.axes is not None else "mesh"
                attrs = np.zeros((n, 12), dtype=np.float32)
                attrs[:, 0:3] = positions
                attrs[:, 3:6] = geom.normals
                if geom.axes is not None:
                    attrs[:, 6:12] = geom.axes.reshape(n, 6)
                colors = np.zeros((n, 4), dtype=np.uint8)
                colors[:, :3] = geom.colors
                buffers += [ctx.buffer(attrs.tobytes()), ctx.buffer(colors.tobytes())]
                content = [
                    (buffers[0], "3f 3f 3f 3f", "in_position", "in_normal", "in_axis_u",
                     "in_axis_v"),
                    (buffers[1], "3f1 1x", "in_color"),
                ]
                prefixes = (("splat", "surfeldepth", "surfelaccum", "feedback") if kind == "splat"
                            else ("mesh", "feedback"))
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
                    basis = (buffers[-1], "4f 3f 3f 3f 3f", "in_basis", "in_grad0", "in_grad1",
                             "in_grad2", "in_grad3")
                if kind == "gaussian":
                    extra["values"] = np.ascontiguousarray(values, dtype=np.float32)
            index = None
            n_faces = 0
            if kind == "mesh":
                faces = np.ascontiguousarray(model.faces, dtype=np.int32)
                n_faces = int(faces.shape[0])
                index = ctx.buffer(faces.tobytes())
                buffers.append(index)
            elif kind == "gaussian":
                index = extra["order"]
            modes = ["plain"] + (["deform"] if k else [])
            sh = extra.get("sh", (0, 0))
            for mode in modes:
                full = content + ([basis] if mode == "deform" and basis is not None else [])
                for prefix in prefixes:
                    vaos[f"{prefix}_{mode}"] = ctx.vertex_array(
                        program(f"{prefix}_{mode}", k, sh, covariance),
                        full,
                        index_buffer=index if prefix in ("mesh", "gauss") else None,
                        index_element_size=4,
                        skip_errors=True,
                    )
        except BaseException:  # a bad argument or a GL error: free what was made so far
            for obj in [*vaos.values(), *buffers]:
                obj.release()
            raise
        return GpuModel(origin, k, lo, hi, n, n_faces, kind, buffers, vaos, storage, **extra)

    # -- draw ---------------------------------------------------------------------------------
    def draw_rgba(
        self,
        gpu: GpuModel,
        camera: Camera | None = None,
        delta_c: np.ndarray | None = None,
        *,
        plain: bool = False,
        blend: bool = True,
    ) -> np.ndarray:
        """Render ``gpu`` deformed by ``delta_c`` (k, 3) (None: undeformed). Returns (H, W, 4)
        uint8, top row first; alpha is the coverage (0 where only background; for Gaussians
        the accumulated opacity). ``blend=False`` draws surfels as opaque depth-tested discs
        (no surface splatting)."""
        if camera is None:
            camera = frame_points([np.stack([gpu.lo, gpu.hi])], aspect=self.size[0] / self.size[1])
        if not gpu.k and not plain and delta_c is not None and np.any(delta_c):
            raise InputError("delta_c: this model was uploaded without a basis (values/gradients)")
        mode = "deform" if (gpu.k and not plain) else "plain"
        view = camera.view(gpu.origin)
        proj = camera.projection(self.size[0] / self.size[1])
        if gpu.kind == "gaussian":
            return self._draw_gaussians(gpu, camera, view, proj, mode, delta_c)
        if gpu.kind == "splat" and blend:
            return self._draw_surfels(gpu, view, proj, mode, delta_c)
        ctx = self.ctx
        vao = gpu.vaos[f"{gpu.kind}_{mode}"]
        self._uniforms(vao.program, gpu, view, proj, mode, delta_c, depth_offset=0.0)
        self._ms.use()
        ctx.viewport = (0, 0, *self.size)
        self._ms.clear(*self.background, 0.0, depth=1.0)
        ctx.enable(ctx.DEPTH_TEST)
        ctx.depth_func = "<"
        ctx.disable(ctx.CULL_FACE | ctx.BLEND)
        if gpu.kind == "mesh":
            vao.render(mode=ctx.TRIANGLES)
        else:
            vao.render(mode=ctx.POINTS, vertices=gpu.n_points)
        ctx.copy_framebuffer(self._resolved, self._ms)
        return self._read_resolved()

    def _read_resolved(self) -> np.ndarray:
        data = self._resolved.read(components=4, alignment=1)
        image = np.frombuffer(data, dtype=np.uint8).reshape(self.size[1], self.size[0], 4)
        return np.ascontiguousarray(image[::-1])

    def _uniforms(self, prog: Any, gpu: GpuModel, view: np.ndarray, proj: np.ndarray, mode: str,
                  delta_c: np.ndarray | None, depth_offset: float | None = None,
                  splat_scale: float | None = None) -> None:
        prog["u_view"].write(gl_bytes(view))
        prog["u_proj"].write(gl_bytes(proj))
        if depth_offset is not None and "u_depth_offset" in prog:
            prog["u_depth_offset"].value = float(depth_offset)
            prog["u_splat_scale"].value = 1.0 if splat_scale is None else float(splat_scale)
        if mode == "deform":
            prog["u_delta"].write(pad_delta(delta_c, gpu.k).tobytes())
            gpu.bind_storage()

    def _draw_surfels(self, gpu: GpuModel, view: np.ndarray, proj: np.ndarray, mode: str,
                      delta_c: np.ndarray | None) -> np.ndarray:
        """Two-pass surface splatting plus the normalising/shading pass (see the module doc)."""
        ctx = self.ctx
        t = self._float_targets()
        ctx.disable(ctx.CULL_FACE | ctx.BLEND)
        ctx.enable(ctx.DEPTH_TEST)
        t["accum"].use()
        ctx.viewport = (0, 0, *self.size)
        t["accum"].clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        # pass 1: depth of the discs pushed back by SURFEL_DEPTH_OFFSET radii
        vao = gpu.vaos[f"surfeldepth_{mode}"]
        self._uniforms(vao.program, gpu, view, proj, mode, delta_c, SURFEL_DEPTH_OFFSET,
                       SURFEL_SCALE)
        t["depth_only"].use()
        ctx.depth_func = "<"
        vao.render(mode=ctx.POINTS, vertices=gpu.n_points)
        # pass 2: weighted colour and normal of every disc in front of that depth
        vao = gpu.vaos[f"surfelaccum_{mode}"]
        self._uniforms(vao.program, gpu, view, proj, mode, delta_c, 0.0, SURFEL_SCALE)
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
        prog["u_viewport"].value = tuple(float(s) for s in self.size)
        prog["u_proj_scale"].value = (float(proj[0, 0]), float(proj[1, 1]))
        prog["u_background"].value = self.background
        self._resolved.use()
        ctx.viewport = (0, 0, *self.size)
        t["resolve"].render(mode=ctx.TRIANGLES, vertices=3)
        return self._read_resolved()

    def _draw_gaussians(self, gpu: GpuModel, camera: Camera, view: np.ndarray, proj: np.ndarray,
                        mode: str, delta_c: np.ndarray | None) -> np.ndarray:
        """Sort by deformed view depth (CPU), then composite back to front (premultiplied)."""
        ctx = self.ctx
        t0 = time.perf_counter()
        deformed = mode == "deform" and delta_c is not None and gpu.values is not None
        order = depth_order(gpu.positions, view, gpu.values if deformed else None,
                            delta_c if deformed else None)
        gpu.order.write(order.tobytes())
        gpu.timings["sort"] = time.perf_counter() - t0
        vao = gpu.vaos[f"gauss_{mode}"]
        prog = vao.program
        self._uniforms(prog, gpu, view, proj, mode, delta_c)
        values = {"u_viewport": tuple(float(s) for s in self.size),
                  "u_eye": tuple(float(v) for v in camera.eye() - gpu.origin),
                  "u_near": float(camera.near)}
        for name, value in values.items():
            if name in prog:  # unused uniforms are compiled away (u_eye without SH bands)
                prog[name].value = value
        gpu.bind_storage()
        t = self._float_targets()
        t["gauss"].use()
        ctx.viewport = (0, 0, *self.size)
        t["gauss"].clear(*self.background, 0.0)
        ctx.disable(ctx.DEPTH_TEST | ctx.CULL_FACE)
        ctx.enable(ctx.BLEND)
        ctx.blend_func = ctx.ONE, ctx.ONE_MINUS_SRC_ALPHA
        try:
            vao.render(mode=ctx.POINTS, vertices=gpu.n_points)
        finally:
            ctx.disable(ctx.BLEND)
        data = np.frombuffer(t["color"].read(), dtype=np.float32)
        image = data.reshape(self.size[1], self.size[0], 4)[::-1]
        gpu.timings["frame"] = time.perf_counter() - t0
        return np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)

    def draw(
        self,
        gpu: GpuModel,
        camera: Camera | None = None,
        delta_c: np.ndarray | None = None,
        *,
        plain: bool = False,
        blend: bool = True,
    ) -> np.ndarray:
        """Like :meth:`draw_rgba`, returning the (H, W, 3) uint8 RGB image."""
        rgba = self.draw_rgba(gpu, camera, delta_c, plain=plain, blend=blend)
        return np.ascontiguousarray(rgba[:, :, :3])

    def draw_float(self, gpu: GpuModel, camera: Camera, delta_c: np.ndarray | None = None, *,
                   plain: bool = False) -> np.ndarray:
        """Gaussians only: the (H, W, 4) float32 premultiplied composite (rgb over the
        background, alpha = 1 - transmittance), top row first, before 8-bit rounding."""
        if gpu.kind != "gaussian":
            raise InputError(f"gpu: expected a Gaussian splat model, got kind {gpu.kind!r}")
        mode = "deform" if (gpu.k and not plain) else "plain"
        self._draw_gaussians(gpu, camera, camera.view(gpu.origin),
                             camera.projection(self.size[0] / self.size[1]), mode, delta_c)
        data = np.frombuffer(self._float_targets()["color"].read(), dtype=np.float32)
        return np.ascontiguousarray(data.reshape(self.size[1], self.size[0], 4)[::-1])

    # -- read-back of the vertex stage ----------------------------------------------------------
    def transform(self, gpu: GpuModel, delta_c: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Run only the vertex stage (transform feedback) and read its outputs back.

        Returns positions (N, 3) float64 (origin added back), normals (N, 3) float32 and
        axes (N, 2, 3) float32: exactly what the rasteriser receives (zero normals and axes
        for Gaussians, whose covariance is handled in their own stage).
        """
        mode = "deform" if gpu.k else "plain"
        vao = gpu.vaos[f"feedback_{mode}"]
        eye = np.eye(4)
        self._uniforms(vao.program, gpu, eye, eye, mode, delta_c)
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
        if self._float is not None:
            for obj in self._float.values():
                obj.release()
            self._float = None


def deformed_positions(
    model: PointModel, values: np.ndarray | None, delta_c: np.ndarray | None
) -> np.ndarray:
    """(N, 3) float64 positions after ``delta_c`` (CPU, for camera framing only)."""
    if values is None or delta_c is None:
        return model.positions
    from splatdeform.deform.arrays import displace

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
    up: str | None = None,
    roll: float = 0.0,
    covariance: str = "jacobian",
) -> Iterator[tuple[Renderer, GpuModel, Camera]]:
    """Upload ``model`` with its basis (values (N, k), gradients (N, k, 3), or None) once,
    frame a camera on the undeformed and the ``delta_c`` (k, 3)-deformed positions (unless
    ``camera`` is given; ``up`` None: the model's convention, see
    :func:`~splatdeform.render.camera.default_up`), and release the GL objects on exit.
    covariance: how Gaussians' covariances deform (``gaussians.covariance``).
    Yields (renderer, gpu, camera)."""
    renderer = Renderer(size)
    try:
        gpu = renderer.upload(model, values, gradients, covariance=covariance)
    except BaseException:
        renderer.release()
        raise
    try:
        if camera is None:
            camera = frame_points(
                [model.positions, deformed_positions(model, values, delta_c)],
                azimuth=azimuth,
                elevation=elevation,
                fov=fov,
                aspect=renderer.size[0] / renderer.size[1],
                up=up or default_up([model]),
                roll=roll,
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
    up: str | None = None,
    roll: float = 0.0,
    covariance: str = "jacobian",
) -> np.ndarray:
    """Render ``model`` (deformed on the GPU by ``delta_c`` (k, 3) when the basis ``values``
    (N, k) / ``gradients`` (N, k, 3) are given) to an (H, W, 3) uint8 image.

    camera: None frames the union of the bounding boxes before and after the deformation
    from ``azimuth`` / ``elevation`` / ``fov`` (degrees) about the ``up`` axis (None: the
    model's convention, -y for 3DGS scenes, else +y), rolled by ``roll`` degrees.
    covariance: how Gaussians' covariances deform (``gaussians.covariance``).
    """
    with deformation_session(model, values, gradients, delta_c, size=size, azimuth=azimuth,
                             elevation=elevation, fov=fov, camera=camera, up=up,
                             roll=roll, covariance=covariance) as (renderer, gpu, cam):
        return renderer.draw(gpu, cam, delta_c)
