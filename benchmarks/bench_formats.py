"""Splat formats: our read and write vs PlayCanvas splat-transform (``-g cpu``), whole process,
one run each, plus peak RSS (``/usr/bin/time -f %M``) against the decoded arrays' size.

    python benchmarks/bench_formats.py              # 1M Gaussians, SH degree 3
    python benchmarks/bench_formats.py --n 200000

Scene: random 3DGS fields (seeded) written as a binary PLY (62 float32 per splat). Write: a
process converting that PLY to the format (both sides read the PLY first); read: a process
decoding the format's file (ours from our write, splat-transform's from its own) and writing
nothing (ours: ``load``; splat-transform: ``--stats null``, which decodes every column and adds
per-column statistics; its bare ``null`` output reads only the header in 3.7.0, so a truncated
file passes: that figure, ``header only``, is printed too but is no decode). ``--busy 2`` runs
everything beside two CPU-busy processes. The decoded arrays: N x 62 float32
(plus N x 3 float64 positions in our model). SOG's write row is its k-means encode (codebooks and
the SH palette; ours: at most 4096 palette entries, splat-transform's: up to 65536), a figure of
its own rather than the "as fast as splat-transform" target; ``--sog-quality`` picks our SH
encoder (default ``fast`` here: the ``reference`` encoder's palette grows to 65536 entries like
splat-transform's, and its k-means costs N x 65536 x 45 per iteration). ``convert``: the whole
scene rotated (``--rotate-euler`` / ``-r``) PLY to PLY, in memory and streamed (64 MB budget).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from data_tools import splat_transform  # noqa: E402

FORMATS = [".compressed.ply", ".spz", ".glb", ".splat", ".sog"]
OURS = ("import warnings, sys; warnings.simplefilter('ignore');"
        "from splatdeform.io import load, save, sog\n"
        "with sog.quality(sys.argv[3] if len(sys.argv) > 3 else None):"
        " save(load(sys.argv[1]), sys.argv[2])")
CONVERT = [sys.executable, "-m", "splatdeform.cli", "convert"]
ANGLES = "30,40,50"
OURS_READ = "import sys; from splatdeform.io import load; load(sys.argv[1])"


def timed(argv: list[str]) -> tuple[float, int]:
    """(wall seconds, peak RSS MiB) of one process (its stdout discarded)."""
    start = time.perf_counter()
    proc = subprocess.run(["/usr/bin/time", "-f", "%M", *argv], stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"failed: {' '.join(argv)}\n{proc.stderr[-2000:]}")
    return wall, int(proc.stderr.strip().splitlines()[-1]) // 1024


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--formats", nargs="*", default=FORMATS)
    parser.add_argument("--their-sog-write", action="store_true",
                        help="also time splat-transform's SOG write (-g cpu: over 7 min at 200k "
                             "Gaussians on the development machine); without it, its SOG read "
                             "decodes our .sog")
    parser.add_argument("--sog-quality", choices=("fast", "reference"), default="fast")
    parser.add_argument("--busy", type=int, default=0,
                        help="run beside this many CPU-busy processes (python 'while 1: pass')")
    args = parser.parse_args()
    busy = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(args.busy)]
    try:
        run(args)
    finally:
        for proc in busy:
            proc.kill()
            proc.wait()


def run(args: argparse.Namespace) -> None:
    from splat_oracle import write_scene

    splat_transform.install()
    st = [*splat_transform.command(), "-g", "cpu", "-q", "-w"]
    decoded_mib = args.n * (62 * 4 + 24) / 2**20
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        src = write_scene(tmp / "scene.ply", args.n, 3, seed=1)
        print(f"{args.n:,} Gaussians, SH3, {src.stat().st_size / 2**20:.0f} MiB PLY; decoded "
              f"arrays {decoded_mib:.0f} MiB; {args.busy} busy processes; load average "
              f"{os.getloadavg()[0]:.1f}")
        print("| format | step | ours s | splat-transform -g cpu s | ratio | ours peak MiB "
              "(x decoded) | theirs peak MiB |")
        print("|---|---|---|---|---|---|---|")
        for ext in args.formats:
            extra = []   # SPZ: both write version 4 by default
            ours_out, theirs_out = tmp / f"ours{ext}", tmp / f"theirs{ext}"
            rows = []
            w_ours = timed([sys.executable, "-c", OURS, str(src), str(ours_out),
                            args.sog_quality])
            their_write = ext != ".splat" and (ext != ".sog" or args.their_sog_write)
            w_theirs = timed([*st, *extra, str(src), str(theirs_out)]) if their_write else None
            rows.append(("write", w_ours, w_theirs))
            r_ours = timed([sys.executable, "-c", OURS_READ, str(ours_out)])
            their_file = str(theirs_out if their_write else ours_out)
            r_theirs = timed([*st, their_file, "--stats", "null"]) if ext != ".glb" else None
            rows.append(("read", r_ours, r_theirs))
            if ext != ".glb":
                rows.append(("header only", None, timed([*st, their_file, "null"])))
            for step, ours, theirs in rows:
                t = f"{theirs[0]:.2f}" if theirs else "n/a"
                ratio = f"{theirs[0] / ours[0]:.2f}x" if theirs and ours else "-"
                tm = f"{theirs[1]}" if theirs else "n/a"
                o = f"{ours[0]:.2f} | " if ours else "- | "
                om = f"{ours[1]} ({ours[1] / decoded_mib:.1f}x)" if ours else "-"
                print(f"| {ext} | {step} | {o}{t} | {ratio} | {om} | {tm} |", flush=True)
            for p in (ours_out, theirs_out):
                p.unlink(missing_ok=True)
        out = tmp / "turned.ply"
        rows = [("convert -r (memory)", timed([*CONVERT, str(src), str(out),
                                              f"--rotate-euler={ANGLES}"]),
                 timed([*st, str(src), "-r", ANGLES, str(tmp / "theirs_turned.ply")])),
                ("convert -r (streamed, 64MB)",
                 timed([*CONVERT, str(src), str(tmp / "s.ply"), f"--rotate-euler={ANGLES}",
                        "--memory-budget", "64MB"]), None)]
        for step, ours, theirs in rows:
            t = f"{theirs[0]:.2f} | {theirs[0] / ours[0]:.2f}x" if theirs else "n/a | -"
            print(f"| .ply | {step} | {ours[0]:.2f} | {t} | {ours[1]} | "
                  f"{theirs[1] if theirs else 'n/a'} |", flush=True)


if __name__ == "__main__":
    main()
