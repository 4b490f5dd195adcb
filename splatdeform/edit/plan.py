"""The one pre-flight of an edit: every path, the stream-or-not choice and the image's view,
decided once, before any work, into an :class:`EditPlan`.

``deform`` (the CLI), batch's workers and the Python API build a plan with :func:`plan_edit`
and hand it to :func:`splatdeform.edit.run.run_edit`, which runs it in memory or passes it on
to :func:`splatdeform.edit.stream.run_stream`; neither checks paths or decides again.

Relative paths of a config (``input``, ``output``, indices files, ``render.camera``) start at
the config file's folder: a config given as a path (``plan_edit("edit.yaml")``,
``sd.run_edit("path/to/edit.yaml")``) resolves against its folder; a config given as a mapping
or an :class:`~splatdeform.edit.config.EditConfig` (it has no file) against ``base_dir``
(default: the current folder).

(Not :mod:`splatdeform.edit.stream.plan`: that is the streamed run's labels and border set.)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from splatdeform.edit.config import EditConfig, input_paths, load_edit, parse_edit
from splatdeform.edit.metaphors import hooked
from splatdeform.edit.stream import StreamOptions, edit_choice
from splatdeform.errors import ConfigError, InputError
from splatdeform.io import SUPPORTED, check_writable, extension_of
from splatdeform.io.plan import IoPlan, plan_io

if TYPE_CHECKING:
    from collections.abc import Callable

    from splatdeform.memory import Choice
    from splatdeform.render.camera import View


@dataclass(frozen=True)
class EditPlan:
    """An edit ready to run: what :func:`plan_edit` checked and decided.

    ``cfg``: the edit; ``base_dir``: where its relative paths start (the config file's
    folder); ``input`` / ``output`` / ``reuse``: the resolved paths (``output`` None: not
    saved); ``streamed``: out of core (:func:`splatdeform.edit.stream.run_stream`) rather than
    in memory; ``options``: budget, Dask and quiet options; ``budget``: the explicit budget in
    bytes (None: the default, half the RAM); ``choice``: the budget rule's decision
    (:func:`splatdeform.memory.choose`; None when Dask was asked for or nothing is saved);
    ``view`` / ``render`` / ``frames``: the edit image's view, path and frame count (None / 0:
    no image); ``source``: the config file, when the edit came from one; ``field`` /
    ``residuals``: the fitted field (``--save-field``) and the pairs' residual CSV
    (``--residuals``) to write after the run (None: not asked); ``io``: every path the run
    reads and writes, checked together (:func:`splatdeform.io.plan.plan_io`; None when
    nothing is saved)."""

    cfg: EditConfig
    base_dir: Path
    input: Path
    output: Path | None
    reuse: Path | None = None
    drop_nonfinite: bool = False
    streamed: bool = False
    options: StreamOptions = StreamOptions()
    budget: int | None = None
    choice: Choice | None = None
    view: View | None = None
    render: Path | None = None
    frames: int = 0
    source: Path | None = None
    field: Path | None = None
    residuals: Path | None = None
    io: IoPlan | None = None


def resolve_config(config: str | Path | dict[str, Any] | EditConfig,
                   base_dir: str | Path | None = None) -> tuple[EditConfig, Path, Path | None]:
    """(the edit, the folder its relative paths start at, its file or None). A path is read,
    and its folder is the base (``base_dir``, when given, wins); a mapping or an EditConfig
    resolves against ``base_dir`` (default: the current folder)."""
    if isinstance(config, EditConfig):
        return config, Path("." if base_dir is None else base_dir), None
    if isinstance(config, dict):
        return parse_edit(config, "edit"), Path("." if base_dir is None else base_dir), None
    if isinstance(config, (str, Path)):
        source = Path(config)
        cfg = load_edit(source)
        return cfg, Path(base_dir) if base_dir is not None else source.resolve().parent, source
    raise TypeError(f"expected an edit config (a file path, a mapping or an EditConfig), got "
                    f"{type(config).__name__}")


def decide(cfg: EditConfig, in_path: Path, options: StreamOptions, budget: int | None, *,
           reuse: str | Path | None = None, drop_nonfinite: bool = False,
           warn: Callable[[str], None] | None = None) -> tuple[bool, Choice | None]:
    """(streamed, the budget rule's choice): streamed when Dask is asked for
    (``options.scheduler``/``workers``; choice None), or when the budget rule
    (:func:`splatdeform.memory.choose`) says stream. ``budget``: the explicit budget
    (``--memory-budget`` / ``memory_budget`` / batch's per-worker figure), a cap: an edit over
    it that cannot stream (its format, or ``--reuse`` / ``--drop-nonfinite`` which need the
    whole model) is refused with one line naming the estimate and the budget. None: half the
    RAM, and the rule from before the cap: over it, ``--reuse``/``--drop-nonfinite`` run in
    memory (``warn`` is told so). Asking for Dask with those options is a ConfigError."""
    whole = "--reuse" if reuse is not None else "--drop-nonfinite" if drop_nonfinite else None
    if options.distributed:
        if whole is not None:
            raise ConfigError("--scheduler/--workers: cannot be combined with --reuse or "
                              "--drop-nonfinite")
        from splatdeform.edit.capable import stream_refusal

        why = stream_refusal(cfg)
        if why:
            raise ConfigError(f"--scheduler/--workers: {why}; run it without them")
        return True, None
    key = options.budget_name or ("--memory-budget" if options.budget is not None else
                                  "memory_budget")
    choice = edit_choice(cfg, in_path, budget, whole=whole, budget_name=key)
    if choice.mode == "refuse":
        raise InputError(choice.message)
    if choice.message and warn is not None:
        warn(choice.message)
    return choice.mode == "stream", choice


def plan_edit(config: str | Path | dict[str, Any] | EditConfig,
              base_dir: str | Path | None = None, *, output: str | Path | None = None,
              save_output: bool = True, reuse: str | Path | None = None,
              drop_nonfinite: bool = False, stream: StreamOptions | None = None,
              warn: Callable[[str], None] | None = None, source: str | Path | None = None,
              output_label: str = "output", reuse_label: str = "reuse cache",
              render: str | Path | None = None, render_label: str = "render.output",
              frames: int = 0, up: str | None = None, roll: float | None = None,
              camera: str | Path | None = None, field: str | Path | None = None,
              residuals: str | Path | None = None) -> EditPlan:
    """The pre-flight, once: raises (one line) before any work, else the plan.

    ``config``: a file path (relative paths resolve against its folder), a mapping or an
    EditConfig (against ``base_dir``, default the current folder; see :func:`resolve_config`).
    ``output`` overrides ``cfg.output`` (``output_label`` names it in errors, e.g.
    ``-o/--output``); ``reuse``: a precomputed deformation file (``reuse_label``).
    ``render``: the edit image's path (``render_label``: the option or key it came from),
    with ``frames`` (``--frames``, else ``render.frames``) and ``up`` / ``roll`` / ``camera``
    (a camera file; wins over the config's view keys) for its view; ``source``: the config
    file (an input no output may replace; default: ``config`` when it is a path);
    ``field`` / ``residuals``: ``--save-field`` and ``--residuals`` (a points: edit's).

    In order: the view (a camera file is read); ``--residuals`` only for a points: edit; no
    output may be an input or another output, whatever the spelling or a link between them
    (:func:`splatdeform.io.plan.plan_io`, the one check, over every path the run
    writes: the model, the reuse cache, the image and its camera file or frames, the field,
    the residuals); the output's extension; the budget rule (``stream``: budget, Dask and
    quiet options; ``warn`` gets its warning); an animation, a field or residuals refused when
    the edit streams (they need the model in memory). With ``save_output`` False nothing is
    checked and the edit runs in memory."""
    cfg, base, file = resolve_config(config, base_dir)
    if reuse is not None:
        from splatdeform.edit.capable import refusal

        why = refusal(cfg, "reusable")
        if why:
            raise ConfigError(f"{why} (`apply` reuses a saved field instead)")
    source = Path(source) if source is not None else file
    in_path = base / cfg.input
    out_path = (Path(output) if output is not None else base / cfg.output) if save_output \
        else None
    reuse = Path(reuse) if reuse is not None else None
    options = stream or StreamOptions()
    view = None
    if render is not None:
        from splatdeform.edit.images import edit_view

        view = edit_view(cfg, up, roll, camera)
    if not save_output:
        return EditPlan(cfg, base, in_path, None, reuse, drop_nonfinite, options=options,
                        view=view, render=None if render is None else Path(render),
                        frames=frames, source=source)
    field = Path(field) if field is not None else None
    residuals = Path(residuals) if residuals is not None else None
    if residuals is not None and not hooked(cfg, "report"):
        raise InputError("--residuals: only for an edit with points: (control-point pairs)")
    outputs: list[tuple[str, Path | None]] = [(output_label, out_path), (reuse_label, reuse),
                                              ("--save-field", field),
                                              ("--residuals", residuals)]
    n_frames = 0
    if render is not None:
        from splatdeform.edit.images import render_frames_count, render_target

        n_frames = render_frames_count(cfg, frames)
        _, files = render_target(render, n_frames, render_label)
        outputs += [(render_label, f) for f in files]
    inputs = [("edit config", source)] if source is not None else []
    inputs += input_paths(cfg, base)
    if camera is not None:
        inputs.append(("--camera/render.camera", Path(camera)))
    io = plan_io(inputs, outputs)
    if extension_of(out_path) not in SUPPORTED:  # a SOG folder's meta.json too
        raise InputError(f"{out_path}: unknown output extension {out_path.suffix!r}; "
                         f"expected one of {', '.join(SUPPORTED)}")
    check_writable(out_path)   # a format only read here (.ksplat): refused before any work
    budget = options.budget_bytes(cfg)
    streamed, choice = decide(cfg, in_path, options, budget, reuse=reuse,
                              drop_nonfinite=drop_nonfinite, warn=warn)
    if streamed and render is not None and n_frames >= 2:
        from splatdeform.edit.images import refuse_streamed_frames

        refuse_streamed_frames()
    if streamed and (field is not None or residuals is not None):
        flag = "--save-field" if field is not None else "--residuals"
        raise InputError(f"{flag}: the edit streams; it needs the in-memory run (raise "
                         "--memory-budget)")
    return EditPlan(cfg, base, in_path, out_path, reuse, drop_nonfinite, streamed, options,
                    budget, choice, view, None if render is None else Path(render), frames,
                    source, field, residuals, io)
