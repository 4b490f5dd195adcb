"""The ``splatdeform`` command.

Exit codes: 0 success, 1 processing failure, 2 bad usage/config/input. Errors are one line on
stderr naming the file or key; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import traceback
from collections.abc import Callable

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
        reuse = str((output or base / cfg.output)) + ".deform.npz"
    result = run_edit(cfg, base, output=output, drop_nonfinite=args.drop_nonfinite, reuse=reuse,
                      log=print)
    render_out = args.render or (str(base / cfg.render.output) if cfg.render else None)
    if render_out:
        from .edit_render import render_result

        render_result(result, cfg, render_out, frames=args.frames)
    print(format_report(result))
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

    for register in _EXTRA_COMMANDS:
        register(sub)
    return parser


_EXTRA_COMMANDS: list[Callable[[argparse._SubParsersAction], None]] = []


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    debug = "--debug" in argv
    try:
        args = build_parser().parse_args(argv)
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
