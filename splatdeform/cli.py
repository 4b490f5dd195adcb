"""The ``splatdeform`` command.

Exit codes: 0 success, 1 processing failure, 2 bad usage/config/input. Errors are one line on
stderr naming the file or key; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import math
import os
import signal
import sys
import traceback
import warnings

from . import __version__
from .basis.names import BACKENDS
from .errors import InputError, NoDeviceWarning, SplatdeformError, error_line, one_line
from .verbs import (
    _show_warning,
    _warn,
    cmd_apply,
    cmd_convert,
    cmd_deform,
    cmd_edit,
    cmd_info,
    cmd_render,
    cmd_select,
)


class _Parser(argparse.ArgumentParser):
    def parse_known_args(self, args=None, namespace=None):  # the words, for error's hints
        self._words = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> None:  # argparse would exit 2 with usage; keep one line
        # main prints "splatdeform: error: "; a verb's parser adds only the verb ("deform: ...")
        verb = self.prog.partition(" ")[2]
        from .suggest import argparse_hint

        message += argparse_hint(self, message)
        raise InputError(f"{verb}: {message}" if verb else message)


# argparse type functions raise ArgumentTypeError: its message survives as the error line
# (a ValueError, InputError included, becomes argparse's "invalid _frames value"); the bounds
# are splatdeform.render.limits', the ones configs and camera files use
def _frames(text: str) -> int:
    from .render.limits import MAX_FRAMES

    try:
        n = int(text)
        if not 0 <= n <= MAX_FRAMES:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer from 0 to {MAX_FRAMES}, got "
                                         f"{text!r}") from None
    return n


def _size(text: str) -> tuple[int, int]:
    from .render.limits import MAX_IMAGE, MIN_IMAGE, size_line

    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if not (MIN_IMAGE <= w <= MAX_IMAGE and MIN_IMAGE <= h <= MAX_IMAGE):
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(size_line(text)) from None
    return w, h


def _number(what: str, lo: float, hi: float):
    """A type function: a finite float within [lo, hi] (``what`` says what it is)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and lo <= value <= hi):
            raise argparse.ArgumentTypeError(f"expected {what} between {lo:g} and {hi:g}, got "
                                             f"{text!r}")
        return value

    parse.__name__ = what.replace(" ", "_")
    return parse


def _fov(text: str) -> float:
    from .render.limits import MAX_FOV, MIN_FOV

    return _number("degrees", MIN_FOV, MAX_FOV)(text)


def _zoom(text: str) -> float:
    from .render.limits import MAX_ZOOM, MIN_ZOOM

    return _number("a factor", MIN_ZOOM, MAX_ZOOM)(text)


def _roll(text: str) -> float:
    from .render.limits import MAX_ROLL

    return _number("degrees", -MAX_ROLL, MAX_ROLL)(text)


def _angle(text: str) -> float:
    from .render.limits import MAX_ANGLE

    return _number("degrees", -MAX_ANGLE, MAX_ANGLE)(text)


def _add_camera_args(p: argparse.ArgumentParser) -> None:
    from .render.camera import UP_AXES

    p.add_argument("--up", choices=UP_AXES, metavar="AXIS",
                   help="up axis, one of +x +y +z -x -y -z; write --up=-y (default: the file's "
                        "convention: -y for 3DGS scenes, +z for LiDAR and geo-referenced scans "
                        "(`info` prints it), else +y)")
    p.add_argument("--roll", type=_roll, default=None, metavar="DEGREES",
                   help="turn the camera about its viewing direction")
    p.add_argument("--camera", metavar="CAMERA.json",
                   help="a camera file (the OUT.camera.json every render writes); wins over "
                        "azimuth/elevation/fov/size/zoom; near/far may be omitted (computed "
                        "from the model)")
    p.add_argument("--zoom", type=_zoom, default=None, metavar="F",
                   help="narrow the view about the target F times (config render.zoom; "
                        "default 1: the model fills the picture)")


def _add_budget_args(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--memory-budget", metavar="SIZE",
                   help=f"{what} (e.g. 512MB, 2GB; config memory_budget; default half the RAM)")
    _add_color_arg(p)


def _add_color_arg(p: argparse.ArgumentParser) -> None:
    from .render.colors import COLOR_MODES

    p.add_argument("--color", choices=COLOR_MODES, metavar="MODE",
                   help="colour by " + " | ".join(COLOR_MODES) + " (config render.color; "
                        "default: the file's colours, else elevation for LiDAR)")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="splatdeform", description="Real-time RBF shape editing of scans.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    parser.add_argument("--version", action="version", version=f"splatdeform {__version__}")
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
    p.add_argument("--backend", choices=BACKENDS,
                   help="basis backend (overrides the config)")
    p.add_argument("--device", help="OpenCL device: 'P:D' indices or a name substring")
    p.add_argument("--reuse", action="store_true",
                   help="reuse/store the precomputed deformation in OUTPUT.deform.npz: a new "
                        "transform with the same regions skips fitting and the basis")
    p.add_argument("--reuse-file", help="like --reuse, with this file")
    p.add_argument("--save-field", metavar="FIELD.npz",
                   help="also write the fitted deformation (for `apply` on other models)")
    p.add_argument("--residuals", metavar="CSV",
                   help="points: edits: write each pair's residual and each check pair's error")
    p.add_argument("--spz-version", type=int, choices=(3, 4),
                   help="SPZ version of a .spz output (default 4; 3 for older readers; config "
                        "save.spz_version)")
    p.add_argument("--render", help="also write a before/after PNG (or GIF with --frames)")
    p.add_argument("--frames", type=_frames, default=0,
                   help="render N frames of the handle moving from identity to the target")
    p.add_argument("--drop-nonfinite", action="store_true",
                   help="drop vertices with NaN/Inf coordinates instead of failing")
    p.add_argument("--memory-budget", metavar="SIZE",
                   help="a cap: when the in-memory estimate exceeds SIZE the scan streams out "
                        "of core (PLY binary, LAS/LAZ), other formats are refused; the peak "
                        "stays within SIZE plus a 256 MB margin for the interpreter and "
                        "libraries (e.g. 512MB, 2GB; config memory_budget; default half the "
                        "RAM, which runs in memory with a warning when --reuse or "
                        "--drop-nonfinite needs it)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="split the scan over this Dask scheduler (tcp://HOST:PORT)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="split the scan over N local Dask worker processes")
    p.add_argument("--quiet", action="store_true",
                   help="no progress lines and no summary on stdout (warnings and errors "
                        "still go to stderr)")
    _add_color_arg(p)
    _add_camera_args(p)
    p.set_defaults(func=cmd_deform)

    p = sub.add_parser("render", help="render a model, or two side by side (before/after)")
    p.add_argument("models", nargs="+", metavar="MODEL", help="one or two model files")
    p.add_argument("-o", "--output", required=True, help="output PNG")
    p.add_argument("--size", type=_size, default="1200x600",
                   help="image size WxH (default 1200x600)")
    p.add_argument("--azimuth", type=_angle, default=30.0)
    p.add_argument("--elevation", type=_angle, default=None,
                   help="degrees above the horizon (default 20; 40 for flat scenes such as "
                        "LiDAR tiles and terrain)")
    p.add_argument("--fov", type=_fov, default=35.0,
                   help="the lens angle, vertical degrees (default 35); the framing fills the "
                        "picture whatever the angle: --zoom narrows the view")
    p.add_argument("--labels", help="comma-separated labels (default: the file names)")
    p.add_argument("--drop-nonfinite", action="store_true")
    _add_budget_args(p, "render a view-independent sample of a model bigger than SIZE")
    _add_camera_args(p)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("select", help="what an edit selects: fixed / handle / free / ring "
                                      "counts, and a preview image coloured by region")
    p.add_argument("config", help="edit YAML file")
    p.add_argument("-o", "--output", help="preview PNG (the model coloured by region)")
    p.add_argument("--drop-nonfinite", action="store_true",
                   help="drop vertices with NaN/Inf coordinates instead of failing")
    _add_budget_args(p, "stream the regions and preview a sample of a scan bigger than SIZE")
    _add_camera_args(p)
    p.set_defaults(func=cmd_select)

    p = sub.add_parser("edit", help="local web editor: pick regions, fit, drag the handle, save")
    p.add_argument("path", metavar="MODEL|EDIT.yaml", help="a model file or an edit YAML")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; next free one)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1: this machine only; any other "
                        "prints a warning, and the URL's token is required all the same)")
    p.add_argument("--save-dir", metavar="DIR",
                   help="the one folder Save writes into, by file name (default: the folder "
                        "of MODEL or EDIT.yaml)")
    p.add_argument("--allow-host", metavar="NAME", action="append",
                   help="a name the browser may reach the editor by (the Host header), "
                        "besides loopback names and addresses and --host; repeatable (others "
                        "are refused: DNS rebinding)")
    p.add_argument("--memory-budget", metavar="SIZE",
                   help="a cap: the editor holds the whole model, its fit and its basis in "
                        "memory; a model whose estimate is over SIZE is refused (e.g. 2GB; "
                        "config memory_budget; default half the RAM)")
    p.add_argument("--viewer", choices=("page",), default="page",
                   help="page (default, the only one): the editor's WebGL2 page, deforming on "
                        "the browser's GPU")
    p.set_defaults(func=cmd_edit)

    p = sub.add_parser("apply", help="apply a field saved by deform --save-field to a model")
    p.add_argument("field", metavar="FIELD.npz")
    p.add_argument("model", metavar="MODEL")
    p.add_argument("-o", "--output", required=True, help="the deformed model")
    p.add_argument("--backend", choices=BACKENDS, help="basis backend (default: the field's)")
    p.add_argument("--memory-budget", metavar="SIZE",
                   help="a cap: over it, binary PLY and LAS/LAZ stream in chunks (e.g. 1GB)")
    p.add_argument("--extrapolate", action="store_true",
                   help="apply the field to a model entirely outside its support (the box of "
                        "its constraints and fitted model), which is otherwise refused")
    p.set_defaults(func=cmd_apply)

    p = sub.add_parser(
        "convert", help="any format to any format, with an optional whole-scene similarity",
        description="Convert IN to OUT (formats by extension). --rotate-euler, --scale and "
                    "--translate take PlayCanvas splat-transform's convention (-r, -s, -t; "
                    "measured with 3.7.0): the same numbers give the same scene in both tools, "
                    "except for .spz inputs, which splat-transform 3.7.0 reads without the SPZ "
                    "specification's RUB -> RDF turn (its scene comes out 180 degrees about x "
                    "from ours; we follow the specification and PlayCanvas's own PLY). "
                    "Euler angles in degrees about the fixed axes x, then y, then z, in "
                    "splat-transform's frame (the file's turned 180 degrees about z); applied "
                    "as rotate, scale, translate. Positions, normals, splat axes, scales, "
                    "rotations and SH follow exactly; nothing else changes.")
    p.add_argument("input", metavar="IN")
    p.add_argument("output", metavar="OUT")
    p.add_argument("--rotate-euler", metavar="X,Y,Z",
                   help="rotate by Euler angles in degrees (splat-transform -r X,Y,Z)")
    p.add_argument("--scale", metavar="S",
                   help="scale uniformly by S, 1e-6 to 1e6 (splat-transform -s)")
    p.add_argument("--translate", metavar="X,Y,Z",
                   help="translate by X,Y,Z (splat-transform -t X,Y,Z)")
    p.add_argument("--memory-budget", metavar="SIZE",
                   help="a cap: over it, binary PLY and LAS/LAZ converted to the same format "
                        "stream in chunks, others are refused (e.g. 512MB; default half the "
                        "RAM)")
    p.add_argument("--drop-nonfinite", action="store_true",
                   help="drop points with NaN/Inf coordinates instead of failing")
    p.add_argument("--sog-quality", choices=("reference", "fast"),
                   help="SOG SH encoder: reference (default; the SH error and size of "
                        "splat-transform's) or fast (a smaller palette: measured 1.5-2.4x the "
                        "SH RMS error, half the file, 30x faster on 150k splats)")
    p.add_argument("--sog-order", choices=("morton", "keep"),
                   help="SOG splat order: morton (default; Z-order by position, as "
                        "splat-transform writes it: smaller files, a SOG read back comes in that "
                        "order) or keep (the input's order)")
    p.add_argument("--pcd-data", choices=("ascii", "binary", "binary_compressed"),
                   help="PCD DATA encoding of OUT (default: the input's; binary for a "
                        "non-PCD input)")
    p.set_defaults(func=cmd_convert)

    from .batch import register as register_batch
    from .examples import register as register_example

    register_batch(sub)
    register_example(sub)
    # --debug after the verb too; SUPPRESS: when absent there, the top level's value stands
    for verb in sub.choices.values():
        verb.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                          help="show tracebacks on errors")
    return parser


class Terminated(BaseException):
    """SIGTERM arrived: unwind like Ctrl-C (temporary files are removed on the way out)."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) arrived. A subclass, not KeyboardInterrupt itself: CPython marks a
    KeyboardInterrupt (that exact type) leaving code run from a string (``namedtuple``'s
    ``eval`` during an import) as unhandled, and then ends the process by SIGINT after main
    returned 130, although main caught it."""


#: The signal that is ending this run (SIGINT / SIGTERM), once one arrived; see _run's fail
_signalled: list[int] = []
#: True while main runs as the process itself (argv None: the console script, python -m): once
#: the run is complete its result is the exit status, and a later Ctrl-C / SIGTERM is ignored
#: instead of ending the process by the signal without a line
_process: list[bool] = [False]


def _quiet_dask_logs() -> None:
    """The process is ending on a signal: Dask's event-loop thread may log what the cut-short
    call left behind (distributed's sync() has logged a NameError traceback through
    "tornado.application"), which would add a traceback to the one "interrupted" line. Silence
    those loggers before the main thread unwinds (only when Dask was imported)."""
    if "distributed" in sys.modules:
        from .dask_client import silence_dask_logs

        silence_dask_logs()


def _on_sigterm(signum, frame) -> None:
    _signalled.append(signal.SIGTERM)
    _quiet_dask_logs()
    raise Terminated()


def _on_sigint(signum, frame) -> None:
    _signalled.append(signal.SIGINT)
    _quiet_dask_logs()
    raise Interrupted()


def _signal_exit() -> int:
    if _signalled[0] == signal.SIGINT:
        print("splatdeform: interrupted", file=sys.stderr)
        return 130
    print("splatdeform: terminated", file=sys.stderr)
    return 143


# OS errors that mean "this path is wrong" (exit 2); the rest (disk full, I/O error) exit 1
_USAGE_ERRNOS = {errno.EACCES, errno.EPERM, errno.ENOENT, errno.ENOTDIR, errno.EISDIR,
                 errno.ENAMETOOLONG, errno.EROFS, errno.EEXIST, errno.ELOOP, errno.EINVAL}


def _os_error_line(exc: OSError) -> tuple[str, int]:
    where = exc.filename if exc.filename is not None else ""
    what = exc.strerror or str(exc) or type(exc).__name__
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        what += " (the disk or the file size limit is full; nothing was written)"
    line = f"{where}: {what}" if where else what
    return line, 2 if exc.errno in _USAGE_ERRNOS else 1


def _stdout_gone() -> int:
    """The reader of stdout went away (``| head``): stop quietly, like other Unix tools."""
    with contextlib.suppress(OSError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    return 141  # 128 + SIGPIPE


def _lossy_writes_as_lines() -> None:
    """A quantised write's note (which properties lose what) is one warning line per write
    (called inside main's ``warnings.catch_warnings``, which restores the hook)."""
    from .io.splats import LossyWriteWarning

    warnings.simplefilter("always", LossyWriteWarning)
    shown = warnings.showwarning

    def show(message, category, *args, **kwargs):
        if issubclass(category, LossyWriteWarning):
            _warn(str(message))
        else:
            shown(message, category, *args, **kwargs)

    warnings.showwarning = show


def main(argv: list[str] | None = None) -> int:
    _process[0] = argv is None
    argv = sys.argv[1:] if argv is None else argv
    debug = "--debug" in argv
    previous = {}
    _signalled.clear()
    with contextlib.suppress(ValueError):  # not in the main thread (tests calling main())
        previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, _on_sigterm)
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            previous[signal.SIGINT] = signal.signal(signal.SIGINT, _on_sigint)
    try:
        with warnings.catch_warnings():
            if not debug:  # numpy RuntimeWarnings must not turn one error line into several
                warnings.simplefilter("ignore", RuntimeWarning)
            warnings.simplefilter("default", NoDeviceWarning)  # but the slow fallback is said
            warnings.showwarning = _show_warning  # ours are one line each
            return _run(argv, debug)
    finally:  # callers in the same process (tests, the API) get their handler back
        for sig, handler in (() if _process[0] else previous.items()):
            with contextlib.suppress(ValueError, TypeError):
                signal.signal(sig, handler)


def _run(argv: list[str], debug: bool) -> int:
    """Parse and run one verb; every failure becomes one line and an exit code."""

    def fail(line: str, code: int) -> int:
        if debug:
            traceback.print_exc()
        if _signalled:  # whatever the unwinding raised (e.g. an import it cut short) was the signal
            return _signal_exit()
        print(f"splatdeform: error: {one_line(line)}", file=sys.stderr)
        return code

    try:
        _lossy_writes_as_lines()  # inside the try: an import here may meet a SIGTERM
        from .basis.kernel_cache import set_note_sink

        set_note_sink(lambda line: print(f"splatdeform: {line}", file=sys.stderr, flush=True))
        args = build_parser().parse_args(argv)
        if args.command == "render" and len(args.models) > 2:
            raise InputError("render: expected one or two model files")
        code = int(args.func(args) or 0)
        sys.stdout.flush()
        if _process[0]:   # complete: one exit status, whenever a signal comes from now on
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, signal.SIG_IGN)
        if _signalled:  # its exception was swallowed (raised inside a finalizer): still honour it
            return _signal_exit()
        return code
    except SplatdeformError as exc:
        return fail(str(exc), exc.exit_code)
    except MemoryError:
        return fail("out of memory", 1)
    except BrokenPipeError:
        return _stdout_gone()
    except OSError as exc:
        return fail(*_os_error_line(exc))
    except KeyboardInterrupt:
        _signalled.insert(0, signal.SIGINT)
        return _signal_exit()
    except Terminated:
        _signalled.insert(0, signal.SIGTERM)
        return _signal_exit()
    except RecursionError:
        return fail("input nested too deeply", 2)
    except Exception as exc:  # a bug: still one line; --debug shows where
        return fail(_internal(exc), 1)
    except BaseException as exc:  # pyo3's PanicException (a Rust panic) is a BaseException
        if type(exc).__name__ != "PanicException":
            raise
        return fail(_internal(exc), 1)


def _internal(exc: BaseException) -> str:
    return (f"internal error: {type(exc).__name__}: {error_line(exc, limit=300, mark='')} "
            "(rerun with --debug for the traceback)")


if __name__ == "__main__":
    sys.exit(main())
