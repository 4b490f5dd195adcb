"""Offscreen rendering with the deforming vertex stage (moderngl, headless EGL): the thin
:class:`Renderer` that uploads a model and dispatches each draw to its pipeline.

One :class:`Renderer` owns framebuffers of one size (:mod:`.targets`). :meth:`Renderer.upload`
sends a model and optionally its deformation basis ONCE; :meth:`Renderer.draw` then renders it
for any delta C with only a 12-float uniform changing per frame (plus, for Gaussians, the
per-frame depth order). Without a basis (or with ``plain=True``) the plain programs render the
stored geometry (the comparison path for CPU-deformed models). Three kinds of model, one
pipeline module each:

- ``gaussian`` (3D Gaussian splats): EWA splatting, :mod:`.gaussians`;
- ``splat`` (surfels and point clouds): surface splatting or opaque discs, :mod:`.surfels`;
- ``mesh``: indexed triangles, :mod:`.meshes`.

Programs are assembled and cached in :mod:`.programs`; the basis goes to the GPU as
:mod:`.packing` lays it out (vertex attributes for k <= 4, a storage buffer for larger k).

Positions are uploaded relative to an ``origin`` (the bounding-box centre, float64) so that
scans with large coordinate offsets keep float32 precision; the deformation is translation
invariant (p' - p and J do not depend on where the origin is).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np

from splatdeform.deform.gaussians import COVARIANCE_MODES, DEFAULT_COVARIANCE
from splatdeform.errors import InputError
from splatdeform.model import PointModel
from splatdeform.render import gaussians, meshes, surfels
from splatdeform.render.camera import DEFAULT_VIEW, Camera, View, frame_points
from splatdeform.render.context import get_context
from splatdeform.render.gpu import GpuModel, set_uniforms
from splatdeform.render.packing import upload_basis
from splatdeform.render.programs import program
from splatdeform.render.splats import splat_geometry
from splatdeform.render.targets import Targets
from splatdeform.render.visibility import check_drawn

BACKGROUND = (255, 255, 255)

__all__ = ["BACKGROUND", "GpuModel", "Renderer", "deformation_session", "deformed_positions",
           "render_image"]


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
        self.targets = Targets(self.ctx, self.size, samples, self.background)

    # -- upload -------------------------------------------------------------------------------
    def upload(
        self,
        model: PointModel,
        values: np.ndarray | None = None,
        gradients: np.ndarray | None = None,
        *,
        fill_holes: bool = True,
        covariance: str = DEFAULT_COVARIANCE,
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
        vaos: dict[str, Any] = {}
        try:
            if model.gaussians is not None:
                part = gaussians.upload(ctx, model, positions, buffers)
            else:
                geom = splat_geometry(model, fill_holes=fill_holes)
                part = (surfels.upload(ctx, positions, geom, buffers) if geom.axes is not None
                        else meshes.upload(ctx, model, positions, geom, buffers))
            k, basis, storage = 0, None, None
            if values is not None:
                k, basis, storage = upload_basis(ctx, values, gradients, n, buffers)
                if part.host_values:
                    part.extra["values"] = np.ascontiguousarray(values, dtype=np.float32)
            sh = part.extra.get("sh", (0, 0))
            for mode in ["plain"] + (["deform"] if k else []):
                full = part.content + ([basis] if mode == "deform" and basis is not None else [])
                for prefix in part.prefixes:
                    vaos[f"{prefix}_{mode}"] = ctx.vertex_array(
                        program(f"{prefix}_{mode}", k, sh, covariance),
                        full,
                        index_buffer=part.index if prefix in ("mesh", "gauss") else None,
                        index_element_size=4,
                        skip_errors=True,
                    )
        except BaseException:  # a bad argument or a GL error: free what was made so far
            for obj in [*vaos.values(), *buffers]:
                obj.release()
            raise
        return GpuModel(origin, k, lo, hi, n, part.n_faces, part.kind, buffers, vaos, storage,
                        **part.extra)

    # -- draw ---------------------------------------------------------------------------------
    def _mode(self, gpu: GpuModel, plain: bool) -> str:
        return "deform" if (gpu.k and not plain) else "plain"

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
        mode = self._mode(gpu, plain)
        view = camera.view(gpu.origin)
        proj = camera.projection(self.size[0] / self.size[1])
        if gpu.kind == "gaussian":
            return gaussians.draw(self.targets, gpu, camera, view, proj, mode, delta_c)
        if gpu.kind == "splat":
            return surfels.draw(self.targets, gpu, view, proj, mode, delta_c, blend=blend)
        return meshes.draw(self.targets, gpu, view, proj, mode, delta_c)

    def draw(self, gpu: GpuModel, camera: Camera | None = None,
             delta_c: np.ndarray | None = None, **flags: bool) -> np.ndarray:
        """Like :meth:`draw_rgba` (``flags``: its ``plain`` and ``blend``), returning the
        (H, W, 3) uint8 RGB image."""
        return np.ascontiguousarray(self.draw_rgba(gpu, camera, delta_c, **flags)[:, :, :3])

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
        set_uniforms(vao.program, gpu, eye, eye, mode, delta_c)
        out = self.ctx.buffer(reserve=gpu.n_points * 12 * 4)
        self.targets.ms.use()  # a surfaceless EGL context has no default framebuffer to draw in
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
        self.targets.release()


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
    view: View = DEFAULT_VIEW,
    *,
    covariance: str = DEFAULT_COVARIANCE,
) -> Iterator[tuple[Renderer, GpuModel, Camera]]:
    """Upload ``model`` with its basis (values (N, k), gradients (N, k, 3), or None) once at
    ``view.size``, frame a camera on the undeformed and the ``delta_c`` (k, 3)-deformed
    positions (unless ``view.camera`` is given; ``view.up`` None: the model's convention, see
    :func:`~splatdeform.render.camera.default_up`), and release the GL objects on exit.
    covariance: how Gaussians' covariances deform (``gaussians.covariance``).
    Yields (renderer, gpu, camera)."""
    renderer = Renderer(view.size)
    try:
        gpu = renderer.upload(model, values, gradients, covariance=covariance)
    except BaseException:
        renderer.release()
        raise
    try:
        camera = view.framed(   # a camera file's missing near/far come from the model
            [model.positions, deformed_positions(model, values, delta_c)], [model],
            renderer.size[0] / renderer.size[1])
        yield renderer, gpu, camera
    finally:
        gpu.release()
        renderer.release()


def render_image(
    model: PointModel,
    view: View = DEFAULT_VIEW,
    *,
    values: np.ndarray | None = None,
    gradients: np.ndarray | None = None,
    delta_c: np.ndarray | None = None,
    covariance: str = DEFAULT_COVARIANCE,
) -> np.ndarray:
    """Render ``model`` (deformed on the GPU by ``delta_c`` (k, 3) when the basis ``values``
    (N, k) / ``gradients`` (N, k, 3) are given) to an (H, W, 3) uint8 image of ``view.size``.

    view: without a camera, frames the robust projected extent of the model before and after
    the deformation from its azimuth / elevation / fov (degrees) and zoom about its ``up`` axis
    (None: the model's convention, :func:`~splatdeform.render.camera.default_up`), rolled by
    ``roll`` degrees. Warns when no part of the model is drawn.
    covariance: how Gaussians' covariances deform (``gaussians.covariance``).
    """
    with deformation_session(model, values, gradients, delta_c, view,
                             covariance=covariance) as (renderer, gpu, cam):
        rgba = renderer.draw_rgba(gpu, cam, delta_c)
        check_drawn(rgba, cam, [model.positions])
        return np.ascontiguousarray(rgba[:, :, :3])
