"""A scan's thumbnails: the whole model before/after (``<stem>.png``, framed as ``render``
frames a model) and, unless ``render.closeup: false``, the changed part before/after
(``<stem>.changed.png``, framed on the points that moved:
:func:`splatdeform.render.compare.closeup_camera`), each with its ``.camera.json``. The
close-up is left out when nothing moved, or when the whole-model image already shows the
changed part nearly as large (less than ``CLOSEUP_GAIN``, 1.3 times, smaller): most of the
model moved.

Both come from one basis evaluation and one upload (in memory), or one read of the input and
output files (a streamed scan, sampled within the budget as ``deform --render`` samples them).
Splats are blended as ``render`` blends them; colours as ``deform --render``.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from splatdeform.edit.config import EditConfig
    from splatdeform.edit.result import EditResult


def render_thumbnails(result: EditResult, cfg: EditConfig, png: str, closeup: str | None, *,
                      input_path: Path, budget: int | None = None) -> str | None:
    """Write the thumbnail ``png`` of ``cfg.render`` (both panels' size, view keys, colour)
    and the close-up ``closeup`` (None: not asked). Returns the close-up's path when it was
    written (not when nothing moved or it would add nothing). A close-up left by an earlier run
    is removed first."""
    from splatdeform.edit.images import edit_view
    from splatdeform.render.camera import camera_sidecar, default_up
    from splatdeform.render.colors import colored

    t0 = time.perf_counter()
    opts = cfg.render
    view = edit_view(cfg, opts.up, opts.roll, opts.camera)
    if closeup is not None:
        for stale in (Path(closeup), camera_sidecar(closeup)):
            stale.unlink(missing_ok=True)
    if result.model is None:   # streamed: the model was never whole
        _streamed(result, input_path, png, closeup, budget, opts.color, view)
    else:
        from splatdeform.deform import full_basis
        from splatdeform.render.compare import render_deformation_comparison

        model = colored(result.model, opts.color, view.up or default_up([result.model]))
        values, gradients = full_basis(result.deformation)
        render_deformation_comparison(model, values, gradients, result.delta_c, png, view,
                                      covariance=cfg.gaussians.covariance, closeup=closeup)
    result.timings["render"] = time.perf_counter() - t0
    return closeup if closeup is not None and Path(closeup).is_file() else None


def _streamed(result: EditResult, input_path: Path, png: str, closeup: str | None,
              budget: int | None, color: str | None, view) -> None:
    """Before/after of a streamed edit from its input and output files, each a sample within
    half the budget (the same seeded rows of both), as ``deform --render`` draws it."""
    from splatdeform.edit.stream import default_budget
    from splatdeform.edit.stream.sample import load_for_render
    from splatdeform.render.camera import default_up
    from splatdeform.render.colors import colored
    from splatdeform.render.compare import render_comparison

    budget = budget or default_budget()
    models = [load_for_render(p, budget, share=0.5).model
              for p in (input_path, result.output)]
    up = view.up or default_up(models)
    before, after = (colored(m, color, up) for m in models)
    if before.n_points == after.n_points and before.colors is not None:
        after = replace(after, colors=before.colors)   # one colour scale: the input's
    render_comparison(before, after, png, view, labels=("before", "after"), closeup=closeup)
