"""The verbs' handlers (``cmd_*``: ``info``, ``deform``, ``select``, ``edit``, ``render``); the
parser and the process around them (signals, error lines, exit codes) are :mod:`splatdeform.cli`'s.
Each handler takes the parsed arguments and returns the exit code; errors are raised (the CLI
turns them into one line)."""

from __future__ import annotations

import argparse
import sys

from .errors import InputError


def cmd_info(args: argparse.Namespace) -> int:
    from .info import describe, format_text, to_json
    from .io import format_fields, load

    model = load(args.model, drop_nonfinite=args.drop_nonfinite)
    info = describe(model)
    from .render.upaxis import up_rule  # the up axis render would use (no GL context)

    info["up_axis"], info["up_reason"] = up_rule([model])
    info.update(format_fields(args.model))
    print(to_json(info) if args.json else format_text(info))
    return 0


def cmd_apply(args: argparse.Namespace) -> int:
    """``apply FIELD.npz MODEL -o OUT`` (:func:`splatdeform.field_apply.apply_file`)."""
    from .field_apply import apply_file
    from .io import READ_ONLY, check_writable, extension_of
    from .memory import budget_bytes

    if extension_of(args.output) in READ_ONLY:   # before the field is read or a folder made
        check_writable(args.output)
    out, streamed = apply_file(args.field, args.model, args.output, backend=args.backend,
                               budget=budget_bytes(args.memory_budget),
                               extrapolate=args.extrapolate)
    print(f"wrote {out}" + (" (streamed within the memory budget)" if streamed else ""))
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    from .conversion import convert, parse_scale, parse_triple, similarity
    from .io.options import writing  # a writer's module only when its option is given
    from .memory import budget_bytes

    _check_budget_alone(args, None)
    sim = similarity(
        parse_triple(args.rotate_euler, "--rotate-euler") if args.rotate_euler else None,
        parse_scale(args.scale) if args.scale is not None else None,
        parse_triple(args.translate, "--translate") if args.translate else None)
    with writing(sog_quality=args.sog_quality, sog_order=args.sog_order,
                 pcd_data=args.pcd_data):
        mode = convert(args.input, args.output, sim, budget=budget_bytes(args.memory_budget),
                       drop_nonfinite=args.drop_nonfinite, log=_warn)
    print(f"wrote {args.output}" + (" (streamed within the memory budget)"
                                    if mode == "stream" else ""))
    return 0


def _warn(message: str) -> None:
    """One warning line on stderr (e.g. a fit that stopped above its tolerance)."""
    print(f"splatdeform: warning: {message}", file=sys.stderr, flush=True)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    _warn(str(message))


def _up_note(view, models) -> None:
    """Say on stderr which up axis a render assumed when the file does not say and the shape
    hints at another (render/upaxis.py's up_note); nothing when --up / a camera decided."""
    from .render.upaxis import up_note

    note = None if view.up or view.camera is not None else up_note(
        [m for m in models if m is not None])
    if note:
        print(f"splatdeform: note: {note}", file=sys.stderr, flush=True)


def cmd_deform(args: argparse.Namespace) -> int:
    from pathlib import Path

    from splatdeform.edit.config import load_edit
    _check_workers(args)
    _check_budget_alone(args, "--reuse/--reuse-file" if args.reuse or args.reuse_file else None)
    cfg = load_edit(args.config)   # a bad config says so before the deform path is imported
    from splatdeform.edit.plan import plan_edit
    from splatdeform.edit.result import format_report
    from splatdeform.edit.run import run_edit

    if args.backend:
        cfg.backend = args.backend
    if args.spz_version:
        cfg.save.spz_version = args.spz_version
    if args.device:
        cfg.device = args.device
    base = Path(args.config).resolve().parent
    output = Path(args.output) if args.output else None
    reuse = args.reuse_file
    if args.reuse and reuse is None:
        reuse = str(output or base / cfg.output) + ".deform.npz"
    render_out = args.render or (str(base / cfg.render.output)
                                 if cfg.render and cfg.render.output else None)
    if cfg.render:   # the options win over the config's render.up / roll / camera
        args.up = args.up or cfg.render.up
        args.roll = cfg.render.roll if args.roll is None else args.roll
        if cfg.render.camera and not args.camera:
            args.camera = str(base / cfg.render.camera)   # relative to the config file
    # the one pre-flight: the view, every path, stream-or-not (run_edit takes the plan as is)
    plan = plan_edit(cfg, base, output=output, reuse=reuse, drop_nonfinite=args.drop_nonfinite,
                     stream=_stream_options(args), warn=_warn, source=args.config,
                     output_label="-o/--output" if output is not None else "output",
                     reuse_label="--reuse-file" if args.reuse_file else "--reuse cache",
                     render=render_out, render_label="--render" if args.render else
                     "render.output", frames=args.frames, up=args.up, roll=args.roll,
                     camera=args.camera, field=args.save_field, residuals=args.residuals)
    view = _with_zoom(plan.view, args.zoom)
    try:
        result = run_edit(plan, log=None if args.quiet else print, warn=_warn)
    except InputError as exc:
        # an error about a config key is said of the config file it came from
        if exc.key is not None:
            raise exc.in_file(args.config) from None
        raise
    if render_out:
        from splatdeform.edit.images import render_result

        budget = _budget(args.memory_budget, cfg.memory_budget)
        image = render_result(result, cfg, render_out, frames=args.frames, view=view,
                              budget=budget, color=args.color, input_path=base / cfg.input)
        _up_note(view, [result.model])
    points = result.points   # a points: edit's pair residuals (None without pairs)
    if args.save_field:
        from splatdeform.field import field_of_edit

        field_of_edit(result, cfg, base).save(args.save_field)
    if args.residuals and points is not None:
        points.write_csv(args.residuals)
    if not args.quiet:   # --quiet: no progress lines, no summary (warnings still on stderr)
        print(format_report(result))
        if points is not None:
            print("\n".join(points.lines()))
        for flag, path in (("field", args.save_field), ("residuals", args.residuals)):
            if path:
                print(f"wrote {flag} {path}")
        if render_out:
            print(f"rendered {image}")
    return 0


def _check_workers(args: argparse.Namespace) -> None:
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers: expected a number of worker processes >= 1, got "
                         f"{args.workers}")
    if args.workers is not None and args.scheduler:
        raise InputError("--workers: not with --scheduler (the scheduler's cluster has its own "
                         "workers); give one of them")


def _check_budget_alone(args: argparse.Namespace, whole: str | None) -> None:
    """--memory-budget streams a big scan; --drop-nonfinite (and ``whole``, e.g. --reuse) need
    the whole model in memory, so together the budget would be silently ignored: refused."""
    if args.memory_budget is None:
        return
    whole = whole or ("--drop-nonfinite" if args.drop_nonfinite else None)
    if whole:
        raise InputError(f"--memory-budget: not with {whole} (that needs the whole model in "
                         "memory, which the budget may not hold); give one of them")


def _stream_options(args: argparse.Namespace):
    from splatdeform.edit.stream import StreamOptions

    return StreamOptions(args.memory_budget, args.scheduler, args.workers, args.quiet)


def cmd_select(args: argparse.Namespace) -> int:
    from pathlib import Path

    from splatdeform.edit.config import input_paths, load_edit
    from splatdeform.edit.images import with_camera_file
    from splatdeform.edit.run import prepare_model
    from splatdeform.edit.selection import (
        format_counts,
        kind_overlays,
        preview_model,
        select_regions,
    )

    from .io.plan import plan_io

    _check_budget_alone(args, None)
    cfg = load_edit(args.config)
    base = Path(args.config).resolve().parent
    if args.output is not None and not args.output.lower().endswith(".png"):
        raise InputError(f"-o/--output: expected a .png file, got {args.output!r}")
    plan_io([("edit config", args.config), *input_paths(cfg, base)],
            [("-o/--output", f) for f in with_camera_file(Path(args.output),
                                                          [Path(args.output)])]
            if args.output is not None else [])
    from splatdeform.edit.stream import should_stream

    budget = _budget(args.memory_budget, cfg.memory_budget)
    streamed = should_stream(cfg, base / cfg.input, budget) and not args.drop_nonfinite
    try:
        if streamed:   # bigger than the budget: regions streamed, a sampled preview
            from splatdeform.edit.stream.select import stream_select

            counts, sample, sel = stream_select(cfg, base, budget,
                                                preview=args.output is not None)
            model = None if sample is None else sample.model
        else:
            model = prepare_model(cfg, base, {}, args.drop_nonfinite)
            sel = select_regions(cfg, model, base)
            counts = sel.counts()
    except InputError as exc:
        raise exc.in_file(args.config) from None
    pairs = None if sel is None else sel.pairs   # a points: edit's; drawn by -o, never fitted
    print(format_counts(counts) + ("  (streamed within the memory budget; rings: see "
                                   "deform)" if streamed else ""))
    if pairs is not None:
        check = "" if pairs[1] is None else f", check pairs {pairs[1].n:,}"
        print(f"pairs {pairs[0].n:,}{check} (select fits nothing: deform reports their "
              "residuals)")
    if args.output is not None:
        from .render import render_comparison

        opts = cfg.render
        if opts:   # --up / --roll / --camera win over render.up / roll / camera
            args.up = args.up or opts.up
            args.roll = opts.roll if args.roll is None else args.roll
            args.camera = args.camera or (str(base / opts.camera) if opts.camera else None)
        view = _edit_view(cfg, args)
        overlays, legend = kind_overlays(cfg, model)
        if pairs is not None:
            from .render.pairs import pair_overlays

            drawn, more = pair_overlays(
                pairs[0].sources, pairs[0].targets, view, [model.positions], [model],
                check=None if pairs[1] is None else (pairs[1].sources, pairs[1].targets))
            overlays, legend = overlays + drawn, legend + more
        color = args.color or "region"   # a preview shows the regions unless --color says
        if color == "region":
            shown = preview_model(model, sel)
            label = (f"fixed (blue) / {counts.moving_name} (orange) / free (grey)"
                     + ("" if streamed else "; rings lighter") + legend)
        else:
            shown = _colored(model, color, view.up, [model])
            label = f"{cfg.input} ({color})"
        render_comparison(shown, None, args.output, view, labels=(label,), overlays=overlays)
        _up_note(view, [model])
        if streamed and counts.points > shown.n_points:
            print(f"rendered {shown.n_points:,} of {counts.points:,} points (memory budget)")
        print(f"wrote {args.output}")
    return 0


def cmd_edit(args: argparse.Namespace) -> int:
    from .editor.page_server import run

    if not 0 <= args.port <= 65535:
        raise InputError(f"--port: expected 0..65535, got {args.port}")
    return run(args.path, host=args.host, port=args.port, save_dir=args.save_dir,
               allow_hosts=tuple(args.allow_host or ()), memory_budget=args.memory_budget)


def _edit_view(cfg, args: argparse.Namespace):
    """The view of an edit's image: the config's ``render`` with --up / --roll / --camera (the
    camera file wins over azimuth/elevation/fov/size and brings the panel size)."""
    from splatdeform.edit.images import edit_view

    return _with_zoom(edit_view(cfg, args.up, args.roll, args.camera), args.zoom)


def _with_zoom(view, zoom: float | None):
    """``view`` with --zoom (None: as it is; it wins over render.zoom)."""
    if view is None or zoom is None:
        return view
    return view.with_options(view.up, view.roll, None, zoom)


def cmd_render(args: argparse.Namespace) -> int:
    from .io.plan import plan_io
    from .render import render_comparison

    size = args.size   # (w, h): checked by the parser (render.limits)
    if not args.output.lower().endswith(".png"):
        raise InputError(f"-o/--output: expected a .png file, got {args.output!r}")
    from pathlib import Path

    from splatdeform.edit.images import with_camera_file

    plan_io([("model", p) for p in args.models]
            + ([("--camera", args.camera)] if args.camera else []),
            [("-o/--output", f) for f in with_camera_file(Path(args.output),
                                                          [Path(args.output)])])
    from dataclasses import replace

    from .render.camera import View

    view = View(azimuth=args.azimuth, elevation=args.elevation,
                fov=args.fov).with_options(args.up, args.roll, args.camera, args.zoom)
    inputs = _render_inputs(args.models, _budget(args.memory_budget), args.drop_nonfinite,
                            explicit=args.memory_budget is not None)
    models = [_colored(r.model, args.color, view.up, [i.model for i in inputs])
              for r in inputs]
    after = models[1] if len(models) > 1 else None
    labels = tuple(args.labels.split(",")) if args.labels else (
        (models[0].path, models[1].path) if after is not None else (models[0].path,))
    if view.camera is None:   # a camera file brings its panel size
        view = replace(view, size=(size[0] // 2, size[1]) if after is not None else size)
    render_comparison(models[0], after, args.output, view, labels=labels)
    _up_note(view, [i.model for i in inputs])
    for r in inputs:
        if r.sampled:
            print(f"{r.model.path}: {r.line()}")
    print(f"wrote {args.output}")
    return 0


def _budget(text: str | None, config_value=None) -> int:
    """--memory-budget (else the config's memory_budget, else half the RAM) in bytes."""
    from splatdeform.edit.stream import budget_bytes, default_budget

    return budget_bytes(text, config_value) or default_budget()


def _render_inputs(paths, budget: int, drop_nonfinite: bool = False,
                   explicit: bool = False) -> list:
    """Each model whole, or a streamed sample when it does not fit its share of ``budget``
    (``explicit``: a --memory-budget cap: a model over it that cannot be sampled is refused)."""
    from splatdeform.edit.stream.sample import load_for_render

    return [load_for_render(p, budget, drop_nonfinite=drop_nonfinite, share=1 / len(paths),
                            explicit=explicit)
            for p in paths]


def _colored(model, mode: str | None, up: str | None, models: list):
    """``model`` coloured by ``mode`` (None: the file's colours, else elevation for LiDAR)
    along the view's up axis (None: the files' convention)."""
    from .render.camera import default_up
    from .render.colors import colored

    return colored(model, mode, up or default_up(models))
