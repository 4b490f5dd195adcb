"""The editor's edit YAML and Save (no web imports): the config mapping of a controller's state,
the default output names, and Save itself (deformed model, edit YAML, before/after PNG).

Everything goes through the pipeline of ``splatdeform deform``: the YAML writer
(:mod:`splatdeform.edit.writer`), the model writer and the renderer, so the saved YAML
reproduces the saved model byte for byte. The controller's :meth:`~.controller.EditorController.
to_yaml_dict`, ``default_paths`` and ``save`` call these functions; they read the controller
through its public attributes and methods only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from splatdeform.edit.writer import edit_yaml, yaml_text

from .. import deform as df
from ..errors import InputError
from ..io import check_output_path, split_extension
from ..io import save as save_model
from ..model import PointModel
from . import selectors as sl
from .state import HandleState, StaleFitError

if TYPE_CHECKING:
    from .controller import EditorController


@dataclass
class SaveResult:
    """Paths written by :meth:`EditorController.save` (image None when not asked)."""

    model: Path
    config: Path
    image: Path | None


def bare_settings(model_path: Path) -> dict[str, Any]:
    """Default settings of an edit started from a bare model (regions filled in later)."""
    return {"input": str(model_path), "output": "unused.ply",
            "regions": {"fixed": [{"indices": [0]}], "handle": [{"indices": [0]}]},
            "handle": {"matrix": np.eye(4).tolist()}}


def to_yaml_dict(ed: EditorController, *, output: str | Path | None = None,
                 config_dir: str | Path | None = None) -> dict[str, Any]:
    """The edit config mapping of ``ed``'s state (what :func:`save` writes as YAML)."""
    cdir = Path(config_dir).resolve() if config_dir is not None else ed.base_dir
    out = Path(output) if output is not None else default_paths(ed)[0]

    def pose(h: HandleState) -> dict[str, Any]:
        return {"region": [sl.to_yaml(x, ed.base_dir) for x in h.selectors],
                "matrix": [[float(v) for v in row] for row in h.matrix]}

    one = ed.curve is None and len(ed.handles) == 1
    return edit_yaml(
        ed.settings, input_path=ed.model_path, output_path=out.resolve(),
        config_dir=cdir, base_dir=ed.base_dir, units=ed.units,
        fixed=[sl.to_yaml(x, ed.base_dir) for x in ed.fixed],
        handle=pose(ed.handles[0]) if one else None,
        handles=None if one else [pose(h) for h in ed.live_handles()],
        curve=None if ed.curve is None else ed.curve.to_yaml(),
        gaussians=ed.model.gaussians is not None)  # the mode the saved splats used


def default_paths(ed: EditorController) -> tuple[Path, Path, Path]:
    """(model, yaml, png) Save writes by default. From a bare MODEL: MODEL_edited.<ext>,
    MODEL_edit.yaml and MODEL_edit.png beside it; from EDIT.yaml: its output, then
    EDIT_edited.yaml and EDIT_edited.png beside the YAML (inputs are never overwritten)."""
    if ed.config_path is not None:
        c = ed.config_path
        return ((ed.base_dir / ed.settings.output).resolve(),
                c.with_name(f"{c.stem}_edited.yaml"), c.with_name(f"{c.stem}_edited.png"))
    m = ed.model_path
    stem, _ = split_extension(m)   # x.compressed.ply -> x_edited.compressed.ply, same format
    ext = m.name[len(stem):]
    return (m.with_name(f"{stem}_edited{ext}"), m.with_name(f"{stem}_edit.yaml"),
            m.with_name(f"{stem}_edit.png"))


def deformed_model(ed: EditorController) -> PointModel:
    """The deformed model exactly as ``splatdeform deform`` computes it for ``ed``'s
    :meth:`~.controller.EditorController.to_config` (float64 :func:`splatdeform.deform.apply`).
    StaleFitError without a fit of the current regions."""
    from splatdeform.edit.plain import control_displacement

    if ed.stale:
        raise StaleFitError("fit: the regions changed since the last fit (or there is none);"
                            " fit again before saving")
    ed.check_poses()
    cfg = ed.to_config()
    delta_c, matrix = control_displacement(cfg, ed.model, ed.deformation)
    deformed = df.apply(ed.deformation, ed.model, delta_c, moving_matrix=matrix,
                        covariance=cfg.gaussians.covariance)
    if not np.isfinite(deformed.positions).all():
        raise InputError("the deformation produced non-finite positions; check the regions "
                         "and the transform")
    return deformed


def save(ed: EditorController, model_path: str | Path | None = None,
         config_path: str | Path | None = None, image_path: str | Path | None = None, *,
         image: bool = True, image_size: tuple[int, int] | None = None) -> SaveResult:
    """Write the deformed model (atomic, never over the input), the edit YAML that
    reproduces it through ``splatdeform deform``, and (``image``) a before/after PNG through
    the project's renderer, ``image_size`` (width, height) pixels for both panels, as
    ``deform --render`` (default: ``render.size`` of the loaded YAML, else its default
    1200 x 600; the view from ``render``'s azimuth, elevation, fov, up and roll). Defaults:
    :func:`default_paths`."""
    r = ed.settings.render
    if image_size is None:
        image_size = tuple(r.size) if r is not None else (1200, 600)
    from ..io import atomic_write

    d_model, d_yaml, d_png = default_paths(ed)
    out = Path(model_path) if model_path is not None else d_model
    ypath = Path(config_path) if config_path is not None else d_yaml
    png = Path(image_path) if image_path is not None else d_png
    inputs = [ed.model_path, ed.config_path]
    check_output_path(out, *inputs)
    check_output_path(ypath, *inputs, out)
    if ypath.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"{ypath}: expected a .yaml edit file name")
    if image:
        from ..render.camera import camera_sidecar

        check_output_path(png, *inputs, out, ypath)
        if png.suffix.lower() != ".png":
            raise InputError(f"{png}: expected a .png image file name")
        check_output_path(camera_sidecar(png), *inputs, out, ypath, png)
    deformed = deformed_model(ed)
    text = yaml_text(to_yaml_dict(ed, output=out, config_dir=ypath.resolve().parent),
                     "splatdeform edit written by the editor; reproduce with:\n"
                     f"  splatdeform deform {ypath.name}")
    written = save_model(deformed, out)
    with atomic_write(ypath) as stream:
        stream.write(text.encode())
    if image:
        from ..render import View, render_comparison

        panel = (max(image_size[0] // 2, 1), image_size[1])
        view = View(size=panel) if r is None else View(
            size=panel, azimuth=r.azimuth, elevation=r.elevation, fov=r.fov, up=r.up,
            roll=r.roll)
        render_comparison(ed.model, deformed, png, view, labels=("before", "after"))
    return SaveResult(written, ypath, png if image else None)
