"""The ``splatdeform`` command.

Exit codes: 0 success, 1 processing failure, 2 bad usage/config/input. Errors are one line on
stderr naming the file or key; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import traceback

from .errors import InputError, SplatdeformError


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # argparse would exit 2 with usage; keep one line
        raise InputError(f"{self.prog}: {message}")


def cmd_info(args: argparse.Namespace) -> int:
    from .info import describe, format_text
    from .io import load

    model = load(args.model, drop_nonfinite=args.drop_nonfinite)
    info = describe(model)
    print(json.dumps(info, indent=2) if args.json else format_text(info))
    return 0


def _warn(message: str) -> None:
    """One warning line on stderr (e.g. a fit that stopped above its tolerance)."""
    print(f"splatdeform: warning: {message}", file=sys.stderr, flush=True)


def cmd_deform(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .config import load_edit
    from .edit import format_report, run_edit

    cfg = load_edit(args.config)
    if args.backend:
        cfg.backend = args.backend
    if args.device:
        cfg.device = args.device
    base = Path(args.config).resolve().parent
    output = Path(args.output) if args.output else None
    reuse = args.reuse_file
    if args.reuse and reuse is None:
        reuse = str(output or base / cfg.output) + ".deform.npz"
    try:
        result = run_edit(cfg, base, output=output, drop_nonfinite=args.drop_nonfinite,
                          reuse=reuse, log=print, warn=_warn)
    except InputError as exc:
        # region/curve/transform errors name the key; add the config file they came from
        if str(exc).split(":")[0].split(".")[0] in ("regions", "handle", "curve", "boundary",
                                                     "fit"):
            raise type(exc)(f"{args.config}: {exc}") from exc
        raise
    render_out = args.render or (str(base / cfg.render.output) if cfg.render else None)
    if render_out:
        from .edit_render import render_result

        render_result(result, cfg, render_out, frames=args.frames)
    print(format_report(result))
    return 0


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w < 16 or h < 16 or w > 8192 or h > 8192:
            raise ValueError
    except ValueError:
        raise InputError(
            f"--size: expected WIDTHxHEIGHT between 16 and 8192, got {text!r}") from None
    return w, h


def cmd_render(args: argparse.Namespace) -> int:
    from .io import check_output_path, load
    from .render import render_comparison

    size = _size(args.size)
    models = [load(p, drop_nonfinite=args.drop_nonfinite) for p in args.models]
    for m in models:
        check_output_path(args.output, m.path)
    if not args.output.lower().endswith(".png"):
        raise InputError(f"-o/--output: expected a .png file, got {args.output!r}")
    after = models[1] if len(models) > 1 else None
    labels = tuple(args.labels.split(",")) if args.labels else (
        (models[0].path, models[1].path) if after is not None else (models[0].path,))
    per = (size[0] // 2, size[1]) if after is not None else size
    render_comparison(models[0], after, args.output, size=per, azimuth=args.azimuth,
                      elevation=args.elevation, fov=args.fov, labels=labels)
    print(f"wrote {args.output}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="splatdeform", description="Real-time RBF shape editing of scans.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("info", help="what the loader sees in a model file")
    p.add_argument("model")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--drop-nonfinite", action="store_true",
                   help="drop vertices with NaN/Inf coordinates instead of failing")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("deform", help="run one edit config (handle or curve)")
    p.add_argument("config", help="edit YAML file")
    p.add_argument("-o", "--output", help="output model (overrides the config's output)")
    p.add_argument("--backend", choices=("auto", "numpy", "opencl"),
                   help="basis backend (overrides the config)")
    p.add_argument("--device", help="OpenCL device: 'P:D' indices or a name substring")
    p.add_argument("--reuse", action="store_true",
                   help="reuse/store the precomputed deformation in OUTPUT.deform.npz: a new "
                        "transform with the same regions skips fitting and the basis")
    p.add_argument("--reuse-file", help="like --reuse, with this file")
    p.add_argument("--render", help="also write a before/after PNG (or GIF with --frames)")
    p.add_argument("--frames", type=int, default=0,
                   help="render N frames of the handle moving from identity to the target")
    p.add_argument("--drop-nonfinite", action="store_true",
                   help="drop vertices with NaN/Inf coordinates instead of failing")
    p.set_defaults(func=cmd_deform)

    p = sub.add_parser("render", help="render a model, or two side by side (before/after)")
    p.add_argument("models", nargs="+", metavar="MODEL", help="one or two model files")
    p.add_argument("-o", "--output", required=True, help="output PNG")
    p.add_argument("--size", default="1200x600", help="image size WxH (default 1200x600)")
    p.add_argument("--azimuth", type=float, default=30.0)
    p.add_argument("--elevation", type=float, default=20.0)
    p.add_argument("--fov", type=float, default=35.0)
    p.add_argument("--labels", help="comma-separated labels (default: the file names)")
    p.add_argument("--drop-nonfinite", action="store_true")
    p.set_defaults(func=cmd_render)

    from .batch import register as register_batch

    register_batch(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    debug = "--debug" in argv
    try:
        args = build_parser().parse_args(argv)
        if args.command == "render" and len(args.models) > 2:
            raise InputError("render: expected one or two model files")
        return int(args.func(args) or 0)
    except SplatdeformError as exc:
        if debug:
            traceback.print_exc()
        print(f"splatdeform: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except MemoryError:
        if debug:
            traceback.print_exc()
        print("splatdeform: error: out of memory", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("splatdeform: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
