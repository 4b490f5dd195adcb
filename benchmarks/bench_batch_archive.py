"""Archive listing: seconds for a batch over N tiny broken members (zip and tar.gz), each checked
from its header while the archive is listed (it was quadratic: 472 s / > 600 s for 10,000).

    python benchmarks/bench_batch_archive.py [--members 10000] [--busy]

--busy runs the same beside two CPU-busy processes. Times include the CLI's start-up.
"""

from __future__ import annotations

import argparse
import io
import os
import subprocess
import sys
import tarfile
import tempfile
import time
import zipfile
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
BAD = (b"ply\nformat binary_little_endian 1.0\nelement vertex 99\nproperty float x\n"
       b"end_header\n")
EDIT = {"regions": {"units": "relative",
                    "fixed": [{"box": {"min": [0, 0, 0], "max": [0.25, 1, 1]}}],
                    "handle": [{"box": {"min": [0.75, 0, 0], "max": [1, 1, 1]}}]},
        "handle": {"transform": {"translate": [0, 0.1, 0]}}, "backend": "numpy"}


def _archive(path: Path, n: int) -> None:
    if path.suffix == ".zip":
        with zipfile.ZipFile(path, "w") as zf:
            for i in range(n):
                zf.writestr(f"m{i:05d}.ply", BAD)
        return
    with tarfile.open(path, "w:gz") as tf:
        for i in range(n):
            info = tarfile.TarInfo(f"m{i:05d}.ply")
            info.size = len(BAD)
            tf.addfile(info, io.BytesIO(BAD))


def _run(root: Path, scans: str, **keys) -> tuple[float, int]:
    cfg = root / f"{Path(scans).stem}.yaml"
    cfg.write_text(yaml.safe_dump({"scans": scans, "edit": EDIT,
                                   "output_dir": f"out_{Path(scans).stem}", **keys}))
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "splatdeform.cli", "batch", str(cfg), "--quiet",
                        "--workers", "1", "--force"], capture_output=True, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    return time.perf_counter() - t0, r.returncode


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--members", type=int, default=10_000)
    ap.add_argument("--busy", action="store_true")
    args = ap.parse_args()
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(2 if args.busy else 0)]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp)
            print(f"{args.members} broken members, {'beside 2 busy processes' if busy else 'idle'}")
            for name in ("many.zip", "many.tar.gz"):
                _archive(root / name, args.members)
                seconds, rc = _run(root, name)
                print(f"  {name:12s} {seconds:6.2f} s  exit {rc}")
    finally:
        for p in busy:
            p.kill()
            p.wait()


if __name__ == "__main__":
    main()
