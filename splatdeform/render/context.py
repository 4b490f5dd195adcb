"""The one place that creates the OpenGL context: a cached standalone EGL context (headless).

Works on a GPU driver and on Mesa's llvmpipe alike. The default (X11/GLX) backend is never used:
it fails without a display. Anything missing (moderngl, libEGL, a GL 3.3 core driver) becomes a
one-line :class:`~splatdeform.errors.DeviceError`.
"""

from __future__ import annotations

import functools
from typing import Any

from splatdeform.errors import DeviceError

MIN_GL_VERSION = 330  # geometry shaders, GLSL 3.30 core


@functools.lru_cache(maxsize=1)
def get_context() -> Any:
    """The process-wide standalone EGL ``moderngl.Context`` (created on first use, cached).

    Raises DeviceError when moderngl, EGL or a GL >= 3.3 core driver is unavailable.
    """
    try:
        import moderngl
    except ImportError as exc:  # pragma: no cover - moderngl is a hard dependency
        raise DeviceError(f"render: the moderngl package is not importable ({exc})") from exc
    try:
        ctx = moderngl.create_standalone_context(backend="egl", require=MIN_GL_VERSION)
    except Exception as exc:
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise DeviceError(
            f"render: cannot create a headless OpenGL {MIN_GL_VERSION // 100}."
            f"{MIN_GL_VERSION // 10 % 10} context through EGL ({reason}); install Mesa's EGL/GL "
            "drivers (e.g. libegl1 libgl1-mesa-dri) or a GPU driver"
        ) from exc
    return ctx


def describe() -> str:
    """One line naming the GL renderer and version, e.g. for benchmark output."""
    ctx = get_context()
    info = ctx.info
    return f"{info.get('GL_RENDERER', '?')} (GL {info.get('GL_VERSION', '?')})"
