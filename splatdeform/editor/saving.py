"""The editor's edit YAML and Save (no web imports): the config mapping of a controller's state,
the default output names, and Save itself (deformed model, edit YAML, before/after PNG).

Everything goes through the pipeline of ``splatdeform deform``: the YAML writer
(:mod:`splatdeform.edit.writer`), the model writer and the renderer, so the saved YAML
reproduces the saved model byte for byte. The controller's :meth:`~.controller.EditorController.
to_yaml_dict`, ``default_paths`` and ``save`` call these functions; they read the controller
through its public attributes and methods only, the ones :class:`EditorState` names (so this
module does not import the controller, which imports it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from splatdeform.edit.writer import edit_yaml, yaml_text

from .. import deform as df
from ..errors import InputError
from ..io import save as save_model
from ..io import split_extension
from ..model import PointModel
from . import selectors as sl
from .state import HandleState, StaleFitError

if TYPE_CHECKING:
    from splatdeform.edit.config import EditConfig
    from splatdeform.edit.selectors import Selector

    from .curve import CurveState


class EditorState(Protocol):
    """What Save reads of an :class:`~.controller.EditorController`: its public state."""

    model: PointModel
    model_path: Path
    config_path: Path | None
    base_dir: Path
    units: str
    settings: EditConfig
    fixed: list[Selector]
    handles: list[HandleState]
    curve: CurveState | None
    points: Any
    points_fit: Any
    deformation: df.Deformation | None

    @property
    def stale(self) -> bool: ...

    def live_handles(self) -> list[HandleState]: ...

    def check_poses(self) -> None: ...

    def to_config(self, *, output: str | Path | None = None,
                  config_dir: str | Path | None = None) -> EditConfig: ...


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


def to_yaml_dict(ed: EditorState, *, output: str | Path | None = None,
                 config_dir: str | Path | None = None) -> dict[str, Any]:
    """The edit config mapping of ``ed``'s state (what :func:`save` writes as YAML)."""
    cdir = Path(config_dir).resolve() if config_dir is not None else ed.base_dir
    out = Path(output) if output is not None else default_paths(ed)[0]

    def pose(h: HandleState) -> dict[str, Any]:
        return {"region": [sl.to_yaml(x, ed.base_dir) for x in h.selectors],
                "matrix": [[float(v) for v in row] for row in h.matrix]}

    one = ed.curve is None and len(ed.handles) == 1 and (ed.points is None
                                                          or bool(ed.live_handles()))
    data = edit_yaml(
        ed.settings, input_path=ed.model_path, output_path=out.resolve(),
        config_dir=cdir, base_dir=ed.base_dir, units=ed.units,
        fixed=[sl.to_yaml(x, ed.base_dir) for x in ed.fixed],
        handle=pose(ed.handles[0]) if one else None,
        handles=None if one else [pose(h) for h in ed.live_handles()],
        curve=None if ed.curve is None else ed.curve.to_yaml(),
        gaussians=ed.model.gaussians is not None)  # the mode the saved splats used
    if ed.points is not None:
        data["points"] = points_yaml(ed, cdir)
        if not ed.fixed:   # pairs alone: no fixed region (an explicit [] is refused)
            data["regions"].pop("fixed", None)
    render = data.get("render")
    if isinstance(render, dict) and render.get("camera"):   # relative to the written YAML
        from splatdeform.edit.writer import relative_path

        render["camera"] = relative_path((ed.base_dir / render["camera"]).resolve(), cdir)
    return data


def points_yaml(ed: EditorState, config_dir: Path) -> dict[str, Any]:
    """The ``points:`` mapping as loaded (:func:`splatdeform.edit.writer.points_mapping`)."""
    from splatdeform.edit.writer import points_mapping

    return points_mapping(ed.points, ed.base_dir, config_dir)


def precompute(cfg, model: PointModel, base_dir: Path) -> tuple[df.Deformation, Any]:
    """Rings, fit and basis of the edit as ``deform`` computes them, and the pairs'
    :class:`~splatdeform.deform.points.PointsFit` of a ``points:`` edit (else None: the
    constraints of the group of a kind without a moving region)."""
    from splatdeform.edit.plain import precompute as plain_precompute

    deformation = plain_precompute(cfg, model, base_dir)
    return deformation, next((g.constraints for g in deformation.groups
                              if g.constraints is not None), None)


def default_paths(ed: EditorState) -> tuple[Path, Path, Path]:
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


def deformed_model(ed: EditorState) -> PointModel:
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
    deformed = df.apply(_one_shot(ed.deformation, ed.model, cfg), ed.model, delta_c,
                        moving_matrix=matrix, covariance=cfg.gaussians.covariance,
                        split=cfg.gaussians.split)
    if not np.isfinite(deformed.positions).all():
        raise InputError("the deformation produced non-finite positions; check the regions "
                         "and the transform")
    return deformed


def _one_shot(deformation, model: PointModel, cfg):
    """``deformation`` with its basis deferred, as ``deform`` builds it for a model written
    once: :func:`splatdeform.deform.apply` then evaluates d(x) and J(x) one-shot from the fit,
    so Save writes the bytes ``splatdeform deform`` writes for the saved YAML (the stored
    basis the page poses with differs from it in float32 rounding)."""
    from dataclasses import replace

    from splatdeform.basis.oneshot import DeferredBasis, deferred_basis

    stored = deformation.basis
    gradients = (stored.with_gradients if isinstance(stored, DeferredBasis)
                 else stored.gradients is not None)
    basis = deferred_basis(model.positions[deformation.free_idx], deformation.fit,
                           gradients=gradients, backend=cfg.backend, device=cfg.device)
    return replace(deformation, basis=basis)


def save(ed: EditorState, model_path: str | Path | None = None,
         config_path: str | Path | None = None, image_path: str | Path | None = None, *,
         image: bool = True, image_size: tuple[int, int] | None = None) -> SaveResult:
    """Write the deformed model (atomic, never over the input), the edit YAML that
    reproduces it through ``splatdeform deform``, and (``image``) the before/after PNG that
    ``deform --render`` writes for that YAML (:func:`render_image`: the same view, colours
    and renderer, pixel for pixel); ``image_size`` (width, height) pixels for both panels
    replaces ``render.size`` (default: the loaded YAML's, else 1200 x 600). Defaults:
    :func:`default_paths`.

    No output is reached through a symbolic link (:func:`splatdeform.io.atomic.pinned_outputs`):
    an output that is a link is refused, each output folder is opened when the names are checked
    and every file is written and renamed relative to it, so a link planted at a name (or in
    place of the folder) after the checks is replaced by the new file, never written through."""
    from ..io.atomic import pinned_outputs

    with pinned_outputs():
        return _save(ed, model_path, config_path, image_path, image=image,
                     image_size=image_size)


def _save(ed: EditorState, model_path: str | Path | None,
          config_path: str | Path | None, image_path: str | Path | None, *,
          image: bool, image_size: tuple[int, int] | None) -> SaveResult:
    from ..io import atomic_write

    d_model, d_yaml, d_png = default_paths(ed)
    out = Path(model_path) if model_path is not None else d_model
    ypath = Path(config_path) if config_path is not None else d_yaml
    png = Path(image_path) if image_path is not None else d_png
    from ..io.plan import plan_io
    from ..render.camera import camera_sidecar

    outputs = [("model", out), ("edit YAML", ypath)]
    if image:
        outputs += [("image", png), ("image's camera file", camera_sidecar(png))]
    # the one check of every path Save writes, as deform's plan makes it (one line naming both)
    plan_io([("input model", ed.model_path), ("edit config", ed.config_path)], outputs)
    if ypath.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"{ypath}: expected a .yaml edit file name")
    view = None
    if image:
        if png.suffix.lower() != ".png":
            raise InputError(f"{png}: expected a .png image file name")
        view = image_view(ed, image_size)   # a bad camera file fails before any write
    deformed = deformed_model(ed)
    text = yaml_text(to_yaml_dict(ed, output=out, config_dir=ypath.resolve().parent),
                     "splatdeform edit written by the editor; reproduce with:\n"
                     f"  splatdeform deform {ypath.name}")
    from ..io.options import writing

    with writing(**ed.to_config().save.model_dump()):   # the save: keys, as deform writes
        written = save_model(deformed, out)
    with atomic_write(ypath) as stream:
        stream.write(text.encode())
    if view is not None:
        render_image(ed, png, view)
    return SaveResult(written, ypath, png if image else None)


def image_view(ed: EditorState, image_size: tuple[int, int] | None = None):
    """The view of Save's PNG: ``deform --render``'s for the editor's YAML
    (:func:`splatdeform.edit.images.edit_view`: ``render``'s size, azimuth, elevation, fov,
    zoom, up, roll and camera file, relative to the config's folder); ``image_size`` (both
    panels) replaces the size unless a camera file brings its own."""
    from dataclasses import replace

    from splatdeform.edit.images import edit_view

    cfg = ed.settings
    r = cfg.render
    camera = str(ed.base_dir / r.camera) if r is not None and r.camera else None
    view = edit_view(cfg, r.up if r else None, r.roll if r else None, camera)
    if image_size is not None and view.camera is None:
        view = replace(view, size=(max(int(image_size[0]) // 2, 1), int(image_size[1])))
    return view


def render_image(ed: EditorState, png: Path, view) -> None:
    """The before/after PNG (and its camera file) of ``ed``'s current fit and pose as
    ``deform --render`` draws it: ``render.color``'s colours, the basis deformed on the GPU
    by the control displacement, ``gaussians.covariance``. One image: ``render.frames`` (an
    animation) is ``deform``'s alone."""
    from splatdeform.edit.plain import control_displacement
    from splatdeform.render.camera import default_up
    from splatdeform.render.colors import colored
    from splatdeform.render.compare import render_deformation_comparison

    cfg = ed.to_config()
    delta_c, _ = control_displacement(cfg, ed.model, ed.deformation)  # as deformed_model
    color = cfg.render.color if cfg.render is not None else None
    model = colored(ed.model, color, view.up or default_up([ed.model]))
    values, gradients = df.full_basis(ed.deformation)
    render_deformation_comparison(model, values, gradients, delta_c, png, view,
                                  covariance=cfg.gaussians.covariance)
