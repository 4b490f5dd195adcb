"""GLSL program assembly, in one place: every shader source gets its host header here, and
every compiled program is cached here (per GL context, per variant).

A program is named ``<kind>_<mode>`` with mode ``plain`` or ``deform`` and kind ``splat``
(opaque discs), ``surfeldepth`` / ``surfelaccum`` (surface splatting passes 1-2), ``mesh``,
``gauss`` (3DGS), ``feedback`` (vertex stage only: the deformed position, normal and axes
captured by transform feedback); or ``resolve`` (surface splatting pass 3).
"""

from __future__ import annotations

from typing import Any

from splatdeform.deform.gaussians import COVARIANCE_MODES, DEFAULT_COVARIANCE
from splatdeform.errors import DeviceError, InputError
from splatdeform.render.context import get_context
from splatdeform.resources import resource_path

MAX_K = 4  # the vertex-attribute path
MAX_STORAGE_K = 128  # the storage-buffer path (u_delta[K] must fit the uniform limits)
STORAGE_GL_VERSION = 430
FEEDBACK_VARYINGS = ("v_position", "v_normal", "v_axis_u", "v_axis_v")

# kinds drawn through deform.vert: (geometry shader, fragment shader, fragment gets shading.glsl)
_SURFACE_STAGES = {
    "splat": ("splat.geom", "splat.frag", True),
    "surfeldepth": ("splat.geom", "surfel_depth.frag", False),
    "surfelaccum": ("splat.geom", "surfel_accum.frag", False),
    "mesh": (None, "mesh.frag", True),
    "feedback": (None, None, False),
}

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


def _compile(ctx: Any, kind: str, deform: bool, k: int, sh: tuple[int, int],
             covariance: str) -> Any:
    if kind == "resolve":
        return ctx.program(vertex_shader=_source("surfel_resolve.vert"),
                           fragment_shader=_source("surfel_resolve.frag", shading=True)
                           + _shader("edl.glsl"))   # eye-dome lighting, declared there
    if kind == "gauss":
        return ctx.program(
            vertex_shader=_source("gauss.vert", deform=deform, k=k, storage=sh[0] > 0, sh=sh,
                                  covariance=covariance),
            geometry_shader=_source("gauss.geom"),
            fragment_shader=_source("gauss.frag"),
        )
    if kind not in _SURFACE_STAGES:  # pragma: no cover - internal names only
        raise InputError(f"program: unknown name {kind!r}")
    geom, frag, shading = _SURFACE_STAGES[kind]
    stages: dict[str, Any] = {"vertex_shader": _source("deform.vert", deform=deform, k=k)}
    if geom is not None:
        stages["geometry_shader"] = _source(geom)
    if frag is not None:
        stages["fragment_shader"] = _source(frag, shading=shading)
    else:
        stages["varyings"] = list(FEEDBACK_VARYINGS)
    return ctx.program(**stages)


def program(name: str, k: int = 0, sh: tuple[int, int] = (0, 0),
            covariance: str = DEFAULT_COVARIANCE) -> Any:
    """A compiled program by name (see the module doc), cached per context.

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
    programs = _programs_of.setdefault(id(ctx), (ctx, {}))[1]
    if key not in programs:
        if (k or sh[0]) and ctx.version_code < STORAGE_GL_VERSION:
            what = f"k = {k} control DOFs" if k else f"SH degree {sh[0]} colours"
            raise DeviceError(
                f"render: {what} need shader storage buffers (OpenGL 4.3), this "
                f"context is OpenGL {ctx.version_code // 100}.{ctx.version_code // 10 % 10}"
            )
        programs[key] = _compile(ctx, kind, deform, k, sh, covariance)
    return programs[key]
