"""Edit configs -> YAML mappings: the inverse of :mod:`splatdeform.edit.config`.

:func:`edit_yaml` writes an edit from its parts (what the editor holds: selectors already in
their config form, handle poses, a curve, the other settings as an :class:`EditConfig`);
:func:`config_yaml` writes a whole parsed config the same way. ``parse_edit`` of either gives
the config back. Paths are written relative to the folder the YAML goes to when inside it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from splatdeform.deform.split import DEFAULT_SPLIT
from splatdeform.edit.config import EditConfig


def relative_path(path: str | Path, base: str | Path) -> str:
    """``path`` relative to ``base`` when it is inside it, else as given (absolute)."""
    path, base = Path(path), Path(base)
    try:
        return str(Path(os.path.relpath(path, base))) if path.is_relative_to(base) else str(path)
    except ValueError:
        return str(path)


def edit_yaml(settings: EditConfig, *, input_path: Path, output_path: Path, config_dir: Path,
              base_dir: Path, units: str, fixed: list[dict[str, Any]],
              handle: dict[str, Any] | None = None, handles: list[dict[str, Any]] | None = None,
              curve: dict[str, Any] | None = None, gaussians: bool = False,
              points: dict[str, Any] | None = None) -> dict[str, Any]:
    """The YAML mapping of an edit.

    input_path, output_path: absolute paths (written relative to ``config_dir`` when inside);
    fixed: the fixed region's selectors in config form; handle: the one-handle form
    (``{"region": [...], "matrix" or "transform": ...}``, its region written as
    ``regions.handle``); handles: the ``handles:`` entries (None or empty: none); curve: the
    ``curve:`` mapping; settings: boundary, fit, normals, backend, device, render (its output
    relative to ``base_dir``), memory budget, the writers' ``save:`` options and gaussians
    (written when set in ``settings`` or ``gaussians``)."""
    data: dict[str, Any] = {
        "input": relative_path(input_path, config_dir),
        "output": relative_path(output_path, config_dir),
        # an empty fixed region is left out (a points: edit alone); an empty list is refused
        "regions": {"units": units, **({"fixed": fixed} if fixed else {})},
    }
    if handle is not None:
        one = dict(handle)
        data["regions"]["handle"] = one.pop("region")
        data["handle"] = one
    elif handles:
        data["handles"] = handles
    if curve is not None:
        data["curve"] = curve
    if points is not None:
        data["points"] = points
    s = settings
    data.update({
        "boundary": s.boundary.model_dump(),
        "fit": s.fit.model_dump(),
        "normals": s.normals,
        "backend": s.backend,  # "auto" stays "auto": the YAML also runs without OpenCL
    })
    if s.device is not None:
        data["device"] = s.device
    if gaussians or "gaussians" in s.model_fields_set:
        data["gaussians"] = {"covariance": s.gaussians.covariance}
        if s.gaussians.split != DEFAULT_SPLIT:   # written only when not the default
            data["gaussians"]["split"] = s.gaussians.split
    if s.render is not None:
        render = s.render.model_dump()
        if s.render.output is not None:
            render["output"] = relative_path((base_dir / s.render.output).resolve(), config_dir)
        data["render"] = render
    if s.memory_budget is not None:
        data["memory_budget"] = s.memory_budget
    saving = {k: v for k, v in s.save.model_dump().items() if v is not None}
    if saving:   # the writers' options (spz_version, sog_quality, ...): the same bytes again
        data["save"] = saving
    return data


def config_yaml(cfg: EditConfig, base_dir: str | Path,
                config_dir: str | Path | None = None) -> dict[str, Any]:
    """The YAML mapping of a parsed config whose paths are relative to ``base_dir``, written
    for a YAML file in ``config_dir`` (default: ``base_dir``); ``parse_edit`` gives ``cfg``
    back (with paths rebased when the folders differ)."""
    base = Path(base_dir).resolve()
    cdir = base if config_dir is None else Path(config_dir).resolve()

    def region(entries) -> list[dict[str, Any]]:   # an indices file: made absolute
        return [e.to_selector().to_config(base) for e in entries]

    def pose(h) -> dict[str, Any]:
        if h.matrix is not None:
            return {"matrix": [[float(v) for v in row] for row in h.matrix]}
        return {"transform": h.transform.model_dump()}

    handle = None if cfg.handle is None else {"region": region(cfg.regions.handle),
                                                **pose(cfg.handle)}
    handles = None if cfg.handles is None else [{"region": region(h.region), **pose(h)}
                                                 for h in cfg.handles]
    return edit_yaml(cfg, input_path=base / cfg.input, output_path=base / cfg.output,
                     config_dir=cdir, base_dir=base, units=cfg.regions.units,
                     fixed=region(cfg.regions.fixed), handle=handle, handles=handles,
                     curve=None if cfg.curve is None else cfg.curve.model_dump(),
                     points=None if cfg.points is None else points_mapping(cfg.points, base,
                                                                          cdir))


def points_mapping(points, base_dir: Path, config_dir: Path) -> dict[str, Any]:
    """The ``points:`` mapping of a parsed one (pairs in ``regions.units``), its pairs files
    rewritten relative to ``config_dir`` (absolute when outside it)."""
    data = points.model_dump(exclude_none=True)
    for key in ("pairs", "check_pairs"):
        entry = data.get(key)
        if isinstance(entry, dict) and "file" in entry:
            entry["file"] = relative_path((Path(base_dir) / entry["file"]).resolve(),
                                          config_dir)
    return data


def yaml_text(data: dict[str, Any], comment: str = "") -> str:
    """The YAML text of an edit mapping (keys in the order written, short lists inline),
    after ``comment`` lines (each prefixed with ``# ``)."""
    head = "".join(f"# {line}\n" for line in comment.splitlines())
    return head + yaml.safe_dump(data, sort_keys=False, default_flow_style=None)
