"""Before/after images of an edit from its precomputed basis (no second load or fit)."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from splatdeform.deform import full_basis
from splatdeform.edit.config import EditConfig, RenderCfg
from splatdeform.edit.result import EditResult
from splatdeform.errors import InputError

if TYPE_CHECKING:
    from splatdeform.render.camera import View


def with_camera_file(image: Path, files: list[Path]) -> list[Path]:
    """``files`` plus the ``OUT.camera.json`` the renderer writes beside ``image`` (when this
    renderer writes one), so the path check covers it too."""
    try:
        from splatdeform.render.camera import camera_sidecar
    except ImportError:
        return files
    return [*files, camera_sidecar(image)]


def render_target(out: str | Path, frames: int, what: str = "render.output"
                  ) -> tuple[Path, list[Path]]:
    """Where an edit's image goes: (the path written, the files written there). One image: a
    .png; frames >= 2: a .gif (a .png name becomes .gif) or a folder of ``frame_NNNN.png``.
    Raises InputError naming ``what`` (the option or key) for any other suffix."""
    from splatdeform.edit.config import check_render_output

    out = Path(out)
    try:
        check_render_output(str(out), frames)
    except ValueError as exc:
        raise InputError(f"{what}: {str(exc).removeprefix('output: ')}") from None
    if frames < 2:
        return out, with_camera_file(out, [out])
    if out.suffix.lower() == ".png":
        out = out.with_suffix(".gif")
    if out.suffix:
        return out, with_camera_file(out, [out])
    return out, with_camera_file(out, [out / f"frame_{i:04d}.png" for i in range(frames)])


def render_frames_count(cfg: EditConfig, frames: int = 0) -> int:
    """The frame count an edit renders: ``--frames`` wins over ``render.frames``."""
    return frames or (cfg.render.frames if cfg.render else 0)


def refuse_streamed_frames() -> None:
    """The InputError of an animation asked of a streamed edit (frames need the model)."""
    raise InputError("--frames/render.frames: an animation needs the model in memory; this "
                     "edit is streamed (raise --memory-budget, or render one image)")


def edit_view(cfg: EditConfig, up: str | None = None, roll: float | None = None,
              camera_file: str | Path | None = None) -> View:
    """The view of an edit's before/after image: one panel is half of ``render.size``'s width,
    azimuth / elevation / fov from ``render``, then the user's ``up``, ``roll`` and camera file
    (which wins over the size and the framing)."""
    from splatdeform.render.camera import View

    opts = cfg.render or RenderCfg()
    return View(size=(opts.size[0] // 2, opts.size[1]), azimuth=opts.azimuth,
                elevation=opts.elevation, fov=opts.fov).with_options(up, roll, camera_file,
                                                                     opts.zoom)


def render_result(result: EditResult, cfg: EditConfig, out: str | Path, *,
                  frames: int = 0, view: View | None = None, budget: int | None = None,
                  color: str | None = None, input_path: Path | None = None) -> Path:
    """Write the before/after PNG (or, with frames >= 2, a GIF/PNG sequence of the handle
    moving from identity to the target). The vertex shader deforms, for any number of control
    DOFs k (k > 4, e.g. curves, reads the basis from a storage buffer); one basis upload.
    Each panel is half of ``render.size``'s width (plus an 18 px label strip on top of the
    before/after image). ``view``: default :func:`edit_view` with ``render.up``,
    ``render.roll`` and ``render.camera`` (a camera file wins over the other view keys).
    ``color``: ``--color`` (else ``render.color``). A streamed result (no model in memory)
    renders ``input_path`` beside the output file, sampled within ``budget`` bytes. A result
    whose splats split (``gaussians.split: auto``) draws the written model, children
    included, beside the input (an animation's frames are drawn unsplit by the shader)."""
    from splatdeform.render import render_deformation_comparison, render_frames

    frames = render_frames_count(cfg, frames)
    opts = cfg.render or RenderCfg(frames=frames)
    covariance = cfg.gaussians.covariance
    target, _ = render_target(out, frames)
    t0 = time.perf_counter()
    if view is None:
        view = edit_view(cfg, opts.up, opts.roll, opts.camera)
    if result.model is None:   # streamed: the model was never whole; render the two files
        render_streamed(result, input_path or Path(cfg.input), target, frames, budget,
                        color or opts.color, view)
        result.timings["render"] = time.perf_counter() - t0
        return target
    from splatdeform.render.camera import default_up
    from splatdeform.render.colors import colored

    model = colored(result.model, color or opts.color, view.up or default_up([result.model]))
    deformed = result.deformed
    if frames < 2 and deformed is not None and deformed.n_points != result.model.n_points:
        from splatdeform.render import render_comparison

        after = colored(deformed, color or opts.color, view.up or default_up([result.model]))
        render_comparison(model, after, target, view, one_scene=True)   # split: the file
        result.timings["render"] = time.perf_counter() - t0
        return target
    values, gradients = full_basis(result.deformation)
    if frames >= 2:
        render_frames(model, values, gradients, result.delta_c, frames, target, view,
                      covariance=covariance)
    else:
        render_deformation_comparison(model, values, gradients, result.delta_c, target, view,
                                      covariance=covariance)
    result.timings["render"] = time.perf_counter() - t0
    return target


def render_streamed(result: EditResult, input_path: Path, target: Path, frames: int,
                    budget: int | None, color: str | None, view: View) -> None:
    """Before/after of a streamed edit from its input and output files, each a sample within
    half the budget when it does not fit (the same seeded rows of both: same count, same
    order); prints the 'rendered N of M points' line."""
    from splatdeform.edit.stream import default_budget
    from splatdeform.edit.stream.sample import load_for_render
    from splatdeform.render import render_comparison
    from splatdeform.render.camera import default_up
    from splatdeform.render.colors import colored

    if frames >= 2:
        refuse_streamed_frames()
    budget = budget or default_budget()
    inputs = [load_for_render(p, budget, share=0.5)
              for p in (input_path, result.output)]
    models = [r.model for r in inputs]
    up = view.up or default_up(models)
    before, after = (colored(m, color, up) for m in models)
    if before.n_points == after.n_points and before.colors is not None:
        after = replace(after, colors=before.colors)   # one colour scale: the input's
    render_comparison(before, after, target, view, labels=("before", "after"),
                      one_scene=True)   # one scene, also when splats split
    if inputs[0].sampled:
        print(inputs[0].line())
