"""The framebuffers of one image size (W, H) that the pipelines draw into: a ``samples``-fold
multisampled colour + depth target (meshes, opaque discs) resolved into an 8-bit one, and,
made on the first blended draw, float targets for surface splatting and Gaussians."""

from __future__ import annotations

from typing import Any

import numpy as np

from splatdeform.render.programs import program


class Targets:
    """ctx: the GL context; size: (W, H); background: RGB in 0..1."""

    def __init__(self, ctx: Any, size: tuple[int, int], samples: int,
                 background: tuple[float, ...]) -> None:
        self.ctx = ctx
        self.size = size
        self.background = background
        samples = min(int(samples), int(ctx.max_samples))
        self.ms = ctx.framebuffer(
            color_attachments=[ctx.renderbuffer(size, 4, samples=samples)],
            depth_attachment=ctx.depth_renderbuffer(size, samples=samples),
        )
        self.resolved = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, 4)])
        self._float: dict[str, Any] | None = None

    def floats(self) -> dict[str, Any]:
        """color, normal (float RGBA textures), depth (a depth texture read as values), and the
        framebuffers accum (color + normal + depth), depth_only, gauss (color); resolve: the
        full-screen vertex array of surface splatting pass 3."""
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

    def draw_opaque(self, vao: Any, primitive: int, vertices: int = -1) -> np.ndarray:
        """Draw ``vao`` depth-tested (no blending, no culling) into the multisampled target
        cleared to the background; returns the resolved (H, W, 4) uint8 image, top row first."""
        ctx = self.ctx
        self.ms.use()
        ctx.viewport = (0, 0, *self.size)
        self.ms.clear(*self.background, 0.0, depth=1.0)
        ctx.enable(ctx.DEPTH_TEST)
        ctx.depth_func = "<"
        ctx.disable(ctx.CULL_FACE | ctx.BLEND)
        vao.render(mode=primitive, vertices=vertices)
        ctx.copy_framebuffer(self.resolved, self.ms)
        return self.read_resolved()

    def read_resolved(self) -> np.ndarray:
        """(H, W, 4) uint8 of the 8-bit target, top row first."""
        data = self.resolved.read(components=4, alignment=1)
        image = np.frombuffer(data, dtype=np.uint8).reshape(self.size[1], self.size[0], 4)
        return np.ascontiguousarray(image[::-1])

    def read_float(self) -> np.ndarray:
        """(H, W, 4) float32 view of the float colour target, top row first."""
        data = np.frombuffer(self.floats()["color"].read(), dtype=np.float32)
        return data.reshape(self.size[1], self.size[0], 4)[::-1]

    def release(self) -> None:
        self.ms.release()
        self.resolved.release()
        if self._float is not None:
            for obj in self._float.values():
                obj.release()
            self._float = None
