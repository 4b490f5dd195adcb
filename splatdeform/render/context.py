"""The one place that creates the OpenGL context: a cached standalone EGL context (headless),
one per thread (an EGL context is current in one thread only: the editor renders its PNGs on its
save thread while another thread may have rendered before).

Works on a GPU driver and on Mesa's llvmpipe alike. The default (X11/GLX) backend is never used:
it fails without a display. Anything missing (moderngl, libEGL, a GL 3.3 core driver) becomes a
one-line :class:`~splatdeform.errors.DeviceError`.
"""

from __future__ import annotations

import threading
from typing import Any

from splatdeform.errors import DeviceError, error_line

MIN_GL_VERSION = 330  # geometry shaders, GLSL 3.30 core


_PER_THREAD = threading.local()


def get_context() -> Any:
    """The calling thread's standalone EGL ``moderngl.Context`` (created on its first use there,
    cached for that thread).

    Raises DeviceError when moderngl, EGL or a GL >= 3.3 core driver is unavailable.
    """
    ctx = getattr(_PER_THREAD, "ctx", None)
    if ctx is None:
        ctx = _PER_THREAD.ctx = _create_context()
    return ctx


def _create_context() -> Any:
    try:
        import moderngl
    except ImportError as exc:  # pragma: no cover - moderngl is a hard dependency
        raise DeviceError(f"render: the moderngl package is not importable ({exc})") from exc
    try:
        ctx = moderngl.create_standalone_context(backend="egl", require=MIN_GL_VERSION)
    except Exception as exc:
        reason = error_line(exc)
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
