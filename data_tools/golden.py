"""Byte-for-byte comparison of two checkouts' outputs and error lines (architecture steps).

``python -m data_tools.golden inputs DIR`` writes the inputs once (generated scans, the shared
data's files written in every splat format by the checkout that runs it, hostile files and edit
configs); ``python -m data_tools.golden run DIR OUT.json`` runs every case with the CLI of the
checkout it is run from (each case in its own subprocess, outputs under DIR/out-<pid>) and
writes, per case, the exit code, the stderr lines (error cases) and the sha256 of every output
file. Run ``inputs`` with the older checkout, then ``run`` with both, and compare the two JSON
files with ``python -m data_tools.golden diff A.json B.json`` (exit 1 on any difference).

Stdout is not compared (it carries timings); stderr is compared for cases that are meant to
fail and for warnings.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

#: the shared data (GOLDEN_SHARED overrides: a worktree elsewhere has no ../shared beside it)
SHARED = Path(os.environ.get("GOLDEN_SHARED",
                             Path(__file__).resolve().parents[2] / "shared" / "data"))
SCANS = ["scans/bunny_res2.ply", "scans/head_surfels.ply", "edge_cases/igea_tristrips.ply",
         "edge_cases/pepper_extra_elements.ply", "edge_cases/horse_big_endian.ply",
         "lidar/vegetation_1_3.las", "lidar/simple.laz", "lidar/extrabytes.las",
         "pcd/osd_learn0_organized.pcd", "splats/guitar_3dgs_sh0.ply",
         "splats/tile_3dgs_sh3.ply"]
SPLAT_EXTS = [".compressed.ply", ".spz", ".sog", ".glb", ".splat"]


def _edit(inp: str, out: str, **extra) -> dict:
    return {"input": inp, "output": out,
            "regions": {"units": "relative",
                        "fixed": [{"box": {"min": [0, 0, 0], "max": [0.3, 1, 1]}}],
                        "handle": [{"box": {"min": [0.7, 0, 0], "max": [1, 1, 1]}}]},
            "handle": {"transform": {"pivot": [0.7, 0.5, 0.5],
                                     "rotate": {"axis": [0, 0, 1], "degrees": 20},
                                     "translate": [0, 0.05, 0]}},
            "fit": {"tolerance": 1e-3, "max_centers": 300}, "backend": "numpy", **extra}


def make_inputs(root: Path) -> None:
    """Write the inputs (models, configs, hostile files) under ``root``."""
    import splatdeform as sd
    from data_tools.synth import bumpy_bar, gaussian_bar

    models = root / "models"
    models.mkdir(parents=True, exist_ok=True)
    sd.save(bumpy_bar(6000, seed=1), models / "bar.ply")
    sd.save(bumpy_bar(6000, seed=2), models / "bar_ascii.ply", text=True)
    splats = gaussian_bar(3000, sh_degree=1, seed=3)
    for ext in [".ply", *SPLAT_EXTS]:
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                sd.save(splats, models / f"gbar{ext}")
    if SHARED.is_dir():
        for rel in SCANS:
            shutil.copyfile(SHARED / rel, models / Path(rel).name)
    bad = root / "bad"
    bad.mkdir(exist_ok=True)
    (bad / "truncated.ply").write_bytes((models / "bar.ply").read_bytes()[:5000])
    (bad / "header.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex x\n"
                                     b"end_header\n")
    (bad / "nan.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                  b"property float y\nproperty float z\nend_header\n"
                                  b"0 0 0\nnan 1 1\n2 2 2\n")
    (bad / "empty.ply").write_bytes(b"")
    (bad / "unknown.xyzw").write_bytes(b"1 2 3\n")
    configs = root / "configs"
    configs.mkdir(exist_ok=True)
    for name in sorted(os.listdir(models)):
        stem = name.split(".")[0]
        ext = name[len(stem):]
        cfg = _edit(f"../models/{name}", f"../OUT/{stem}_def{ext}")
        (configs / f"def_{name}.yaml").write_text(yaml.safe_dump(cfg))
    bar = "../models/bar.ply"
    cases = {
        "unknown_key": {**_edit(bar, "../OUT/x.ply"), "fitt": {}},
        "wrong_type": {**_edit(bar, "../OUT/x.ply"), "fit": {"tolerance": "small"}},
        "empty_region": _edit(bar, "../OUT/x.ply", regions={
            "units": "relative", "fixed": [{"box": {"min": [0, 0, 0], "max": [0.3, 1, 1]}}],
            "handle": [{"box": {"min": [2, 2, 2], "max": [3, 3, 3]}}]}),
        "overlap": _edit(bar, "../OUT/x.ply", regions={
            "units": "relative", "fixed": [{"box": {"min": [0, 0, 0], "max": [0.8, 1, 1]}}],
            "handle": [{"box": {"min": [0.7, 0, 0], "max": [1, 1, 1]}}]}),
        "degenerate_handle": _edit(bar, "../OUT/x.ply", handle={"transform": {"scale": 0}}),
        "missing_input": _edit("../models/nothere.ply", "../OUT/x.ply"),
        "output_is_input": _edit(bar, bar),
        "bad_extension": _edit(bar, "../OUT/x.abc"),
    }
    for name, cfg in cases.items():
        (configs / f"err_{name}.yaml").write_text(yaml.safe_dump(cfg))


def _cases(root: Path) -> list[tuple[str, list[str], bool]]:
    """(name, CLI arguments with OUT for the output folder, expected to fail)."""
    out = []
    for cfg in sorted((root / "configs").glob("def_*.yaml")):
        out.append((cfg.name, ["deform", str(cfg)], False))
    for cfg in sorted((root / "configs").glob("err_*.yaml")):
        out.append((cfg.name, ["deform", str(cfg)], True))
    for cfg in ["def_bar.ply.yaml", "def_vegetation_1_3.las.yaml", "def_simple.laz.yaml"]:
        if (root / "configs" / cfg).exists():
            out.append((f"stream_{cfg}", ["deform", str(root / "configs" / cfg),
                                          "--memory-budget", "160MB"], False))
    for model in sorted((root / "models").iterdir()):
        out.append((f"info_{model.name}", ["info", "--json", str(model)], False))
    for model in sorted((root / "bad").iterdir()):
        out.append((f"info_bad_{model.name}", ["info", str(model)], True))
        out.append((f"render_bad_{model.name}", ["render", str(model), "-o", "OUT/b.png"], True))
    for model in ["bar.ply", "gbar.spz", "bunny_res2.ply", "vegetation_1_3.las"]:
        if (root / "models" / model).exists():
            out.append((f"render_{model}", ["render", str(root / "models" / model), "-o",
                                            f"OUT/{model}.png", "--size", "320x240"], False))
    out.append(("select_bar", ["select", str(root / "configs" / "def_bar.ply.yaml"), "-o",
                               "OUT/select.png"], False))
    out.append(("usage", ["deform"], True))
    out.append(("unknown_flag", ["info", "--nope", "x"], True))
    return out


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run_cases(root: Path, report: Path, only: str | None = None) -> None:
    results = {}
    for name, args, fails in _cases(root):
        if only and only not in name:
            continue
        work = root / f"out-{os.getpid()}"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir()
        (root / "OUT").unlink(missing_ok=True)
        (root / "OUT").symlink_to(work.name)
        args = [a.replace("OUT/", f"{work}/") for a in args]
        res = subprocess.run([sys.executable, "-m", "splatdeform.cli", *args],
                             capture_output=True, text=True, timeout=600, cwd=root)
        files = {}
        for p in sorted(work.rglob("*")):
            if p.is_file() and not p.name.endswith(".json"):
                files[str(p.relative_to(work))] = _digest(p)
            elif p.is_file():   # camera files hold floats formatted by json: compare whole
                files[str(p.relative_to(work))] = _digest(p)
        stderr = [ln.replace(str(work), "OUT") for ln in res.stderr.splitlines()
                  if ln.strip() and (fails or "warning" in ln.lower())]
        results[name] = {"exit": res.returncode, "stderr": stderr, "files": files}
        if res.returncode != 0 and not fails:
            results[name]["unexpected"] = res.stderr[-2000:]
        print(f"{name}: exit {res.returncode}, {len(files)} file(s)", flush=True)
        shutil.rmtree(work, ignore_errors=True)
    (root / "OUT").unlink(missing_ok=True)
    report.write_text(json.dumps(results, indent=1, sort_keys=True))


def diff(a: Path, b: Path) -> int:
    ra, rb = json.loads(a.read_text()), json.loads(b.read_text())
    bad = 0
    for name in sorted(set(ra) | set(rb)):
        if ra.get(name) != rb.get(name):
            bad += 1
            print(f"DIFF {name}:\n  A: {ra.get(name)}\n  B: {rb.get(name)}")
    print(f"{len(set(ra) | set(rb))} cases, {bad} differ")
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("inputs").add_argument("dir", type=Path)
    r = sub.add_parser("run")
    r.add_argument("dir", type=Path)
    r.add_argument("report", type=Path)
    r.add_argument("--only")
    d = sub.add_parser("diff")
    d.add_argument("a", type=Path)
    d.add_argument("b", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "inputs":
        make_inputs(args.dir)
        return 0
    if args.cmd == "run":
        run_cases(args.dir.resolve(), args.report.resolve(), args.only)
        return 0
    return diff(args.a, args.b)


if __name__ == "__main__":
    sys.exit(main())
