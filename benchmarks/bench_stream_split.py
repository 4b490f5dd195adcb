"""The cost of ``gaussians.split: auto`` on a streamed ``deform`` (issue 46 item 3): the split
test pass plus pass 5 against pass 5 unsplit, on the generated scene of 150,000 surface splats
(``bench_needles.surface_scene``) bent 60 degrees, streamed under a 64 MB budget; and whether
the streamed file equals the in-memory one byte for byte.

    python benchmarks/bench_stream_split.py [--splats 150000] [--repeats 3] [--budget 64MB]

Prints one JSON line per run (mode, apply = split test + pass 5, split_test, pass5, split
counts) and a summary with the medians. Runs in this process, one after another.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_needles import edit_config, surface_scene  # noqa: E402

from splatdeform.edit.config import parse_edit  # noqa: E402
from splatdeform.edit.run import run_edit  # noqa: E402
from splatdeform.edit.stream import run_stream  # noqa: E402
from splatdeform.io import save  # noqa: E402
from splatdeform.memory import parse_size  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--splats", type=int, default=150_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--budget", default="64MB")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        model = surface_scene(args.splats)
        save(model, folder / "x.ply")
        edit = edit_config(model, 60.0, 0.0)
        runs: dict[str, list[dict]] = {"off": [], "auto": []}
        for _ in range(args.repeats):
            for mode in ("off", "auto"):
                cfg = parse_edit(dict(edit, gaussians={"split": mode}), "bench")
                r = run_stream(cfg, folder, output=folder / f"{mode}.ply", quiet=True,
                               budget=parse_size(args.budget))
                row = {"mode": mode, "apply_s": r.timings["apply"],
                       "split_test_s": r.timings.get("split_test", 0.0),
                       "pass5_s": r.timings["apply"] - r.timings.get("split_test", 0.0),
                       "chunk": r.stats.get("chunk"),
                       **{k: v for k, v in r.stats.items() if k.startswith("split_")}}
                runs[mode].append(row)
                print(json.dumps(row))
        mem = run_edit(parse_edit(dict(edit), "bench"), folder, output=folder / "mem.ply")
        same = (folder / "mem.ply").read_bytes() == (folder / "auto.ply").read_bytes()

        def med(mode: str, key: str) -> float:
            return float(np.median([r[key] for r in runs[mode]]))

        print(json.dumps({
            "summary": True, "splats": args.splats, "budget": args.budget,
            "apply_off_s": med("off", "apply_s"), "apply_auto_s": med("auto", "apply_s"),
            "split_test_s": med("auto", "split_test_s"), "pass5_auto_s": med("auto", "pass5_s"),
            "ratio": med("auto", "apply_s") / med("off", "apply_s"),
            "in_memory_apply_auto_s": mem.timings["apply"],
            "streamed_equals_in_memory": same}))


if __name__ == "__main__":
    main()
