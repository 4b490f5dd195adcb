"""The format table (issue 33 item 1): every format declares itself once in
:mod:`splatdeform.io.declare`, and ``splatdeform.io`` merges the declarations.

- every declared extension loads and saves a small generated model where the format writes;
- each format's header probe counts what the loader loads (the splat formats from the count
  their header declares);
- no ``.suffix`` decides a format outside ``splatdeform/io/`` (one extension parser,
  :func:`splatdeform.io.extension_of`);
- batch derives ``x_deformed.compressed.ply`` (same format) from ``x.compressed.ply``;
- an SPZ that declares 10M splats in 1 MB is refused by ``deform --memory-budget 200MB`` from
  its declared count (one line naming the estimate and the budget).
"""

from __future__ import annotations

import gzip
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

import splatdeform as sd
from data_tools.synth import bumpy_bar, gaussian_bar
from splatdeform import memory
from splatdeform.io import FORMATS, SOG_META, extension_of, split_extension

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "splatdeform"
SPLAT_KEYS = [ext for ext, fmt in FORMATS.items() if fmt.lossy or fmt.module == "gltf"]
POINT_KEYS = [ext for ext in FORMATS if ext not in SPLAT_KEYS]
READ_ONLY = {".ksplat"}
NEEDS = {".xyz": "open3d", ".xyzn": "open3d", ".pts": "open3d", ".laz": "lazrs"}


def _path(folder: Path, ext: str) -> Path:
    if ext == SOG_META:
        (folder / "sogdir").mkdir()
        return folder / "sogdir" / SOG_META
    return folder / f"model{ext}"


def _save(model, path: Path) -> Path:
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")   # the lossy formats say what they lose
        return sd.save(model, path)


@pytest.fixture(scope="module")
def models():
    return {"splats": gaussian_bar(400, sh_degree=1, seed=3), "points": bumpy_bar(500, seed=1)}


@pytest.mark.parametrize("ext", [e for e in FORMATS if e not in READ_ONLY])
def test_every_declared_extension_saves_loads_and_probes_its_count(ext, models, tmp_path):
    """Every writable format (READ_ONLY ones are made by their reader's tests from their own
    library's files)."""
    if ext in NEEDS:
        pytest.importorskip(NEEDS[ext])
    model = models["splats" if ext in SPLAT_KEYS else "points"]
    path = _save(model, _path(tmp_path, ext))
    loaded = sd.load(path)
    assert loaded.n_points == model.n_points
    cost = memory.file_cost(path)
    if FORMATS[ext].probe is not None:
        assert cost.points == loaded.n_points, ext
        assert cost.load_bytes > 0 and cost.record_bytes > 0


def test_table_is_merged_from_the_declarations_in_the_documented_order():
    assert tuple(FORMATS) == (".ply", ".compressed.ply", ".splat", ".ksplat", ".spz", ".sog",
                              "meta.json",
                              ".glb", ".gltf", ".pcd", ".xyz", ".xyzn", ".pts", ".las", ".laz")
    assert sd.io.LIDAR_EXTENSIONS == (".las", ".laz")
    assert set(sd.io.COSTED) == set(FORMATS) - {".xyz", ".xyzn", ".pts"}


def test_one_extension_parser():
    assert extension_of("a/x.compressed.ply") == ".compressed.ply"
    assert extension_of("X.Compressed.PLY") == ".compressed.ply"
    assert extension_of("dir/meta.json") == "meta.json"
    assert extension_of("x.PLY") == ".ply" and extension_of("noext") == ""
    assert split_extension("X.Compressed.PLY") == ("X", ".compressed.ply")
    assert split_extension("scan.v2.LAZ") == ("scan.v2", ".laz")
    assert split_extension("noext") == ("noext", "")


def test_splat_probes_count_what_the_header_declares(tmp_path):
    """The estimate of a splat file comes from its declared count, not from its size: a 1 MB
    SPZ declaring 10M splats is estimated from 10M (the probe reads only its header)."""
    path = tmp_path / "big.spz"
    path.write_bytes(_declaring_spz(10_000_000))
    assert path.stat().st_size < 1.2 * 2**20
    cost = memory.file_cost(path)
    assert cost.points == 10_000_000
    assert cost.load_bytes > 10_000_000 * 20


# --------------------------------------------------------------------------------------------
# no .suffix format decision outside splatdeform/io/

#: ``.suffix`` uses outside io/ that are not format decisions, by their line (whatever module
#: holds it): why
NOT_FORMATS = {
    'if path.suffix.lower() in (".yaml", ".yml"):': "an edit file (editor)",
    'if ypath.suffix.lower() not in (".yaml", ".yml"):': "an edit file (editor save)",
    'if png.suffix.lower() != ".png":': "an image (editor save)",
    'if target.suffix in (".js", ".mjs"):': "a web asset's type (page server)",
    'elif target.suffix in (".glsl", ".vert", ".frag"):': "a web asset's type (page server)",
    "suffix = Path(output).suffix.lower()": "an image or GIF output (render config)",
    'if out.suffix.lower() == ".png":': "an image output",
    "if out.suffix:": "an image output",
    'raise InputError(f"{out_path}: unknown output extension {out_path.suffix!r}; "':
        "names an unknown extension in an error line (decided by extension_of)",
    'if path.suffix == ".npy":': "an indices file",
    'return p.with_name(f"{p.stem if p.suffix else p.name}.camera.json")':
        "an image's camera sidecar",
    'if out.suffix and out.suffix.lower() != ".gif":': "a GIF output",
    'if out.suffix.lower() == ".gif":': "a GIF output",
    'if path.suffix.lower() == ".zip":': "an archive's kind (batch sources)",
}
#: format decisions by ``.suffix`` in modules owned elsewhere, to move onto
#: ``splatdeform.io.extension_of`` / ``split_extension`` (each is a double-extension bug:
#: ``x.compressed.ply`` taken as ``.ply``); remove an entry when it is fixed
PENDING: dict[str, str] = {}
SUFFIX = re.compile(r"\.suffix(es)?\b")


def suffix_uses() -> dict[str, list[str]]:
    """Every stripped source line outside io/ that uses ``.suffix``: the modules holding it."""
    found: dict[str, list[str]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel.startswith("io/"):
            continue
        for line in path.read_text().splitlines():
            if SUFFIX.search(line):
                found.setdefault(line.strip(), []).append(rel)
    return found


def test_no_suffix_decides_a_format_outside_io():
    uses = suffix_uses()
    unknown = sorted((uses[line], line) for line in uses.keys() - NOT_FORMATS.keys()
                     - PENDING.keys())
    assert not unknown, ("a format decided by `.suffix` outside splatdeform/io/ (use "
                         f"splatdeform.io.extension_of / split_extension): {unknown}")


def test_the_suffix_scan_sees_the_uses_it_allows():
    """The allow-lists name real lines (a stale entry would hide a new use written the same
    way elsewhere)."""
    uses = suffix_uses()
    assert not sorted(NOT_FORMATS.keys() - uses.keys()), "stale NOT_FORMATS entries"
    assert not sorted(PENDING.keys() - uses.keys()), "fixed PENDING entries: remove them"


# --------------------------------------------------------------------------------------------
# batch: a compressed PLY's output keeps its format


def _edit() -> dict:
    return {"regions": {"units": "relative",
                        "fixed": [{"box": {"min": [0, 0, 0], "max": [0.3, 1, 1]}}],
                        "handle": [{"box": {"min": [0.7, 0, 0], "max": [1, 1, 1]}}]},
            "handle": {"transform": {"translate": [0, 0.05, 0]}}, "backend": "numpy"}


def test_batch_output_of_a_compressed_ply_keeps_its_format(models, tmp_path):
    from splatdeform.batch.config import deformed_name, load_batch

    assert deformed_name("x.compressed.ply") == "x_deformed.compressed.ply"
    assert deformed_name("Scan.LAZ") == "Scan_deformed.laz"
    scans = tmp_path / "scans"
    scans.mkdir()
    _save(models["splats"], scans / "x.compressed.ply")
    _save(models["points"], scans / "y.ply")
    cfg = tmp_path / "batch.yaml"
    cfg.write_text(yaml.safe_dump({"scans": "scans", "edit": _edit(), "output_dir": "out"}))
    outputs = sorted(Path(job.output).name for job in load_batch(cfg).jobs)
    assert outputs == ["x_deformed.compressed.ply", "y_deformed.ply"]
    assert extension_of(outputs[0]) == ".compressed.ply"


# --------------------------------------------------------------------------------------------
# an explicit budget caps the splat formats: refused from the declared count


def _declaring_spz(count: int) -> bytes:
    """A 1 MB gzip'd SPZ v3 (SH degree 0) whose header declares ``count`` splats (its body is
    1 MiB of incompressible bytes: far short of what it declares)."""
    from splatdeform.io import spz

    head = spz.HEADER.pack(spz.MAGIC, 3, count, 0, 12, 0, 0)
    body = np.random.default_rng(33).integers(0, 256, 2**20, dtype=np.uint8).tobytes()
    return gzip.compress(head + body, compresslevel=1)


def test_deform_budget_refuses_an_spz_from_its_declared_count(tmp_path):
    spz_path = tmp_path / "big.spz"
    spz_path.write_bytes(_declaring_spz(10_000_000))
    cfg = tmp_path / "edit.yaml"
    cfg.write_text(yaml.safe_dump({**_edit(), "input": "big.spz", "output": "out.spz"}))
    res = subprocess.run([sys.executable, "-m", "splatdeform.cli", "deform", str(cfg),
                          "--memory-budget", "200MB"], capture_output=True, text=True,
                         cwd=tmp_path, timeout=120)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2, res.stderr
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert "big.spz" in lines[0] and "in-memory estimate" in lines[0], lines
    assert "200 MB" in lines[0] or "200MB" in lines[0] or "200.0 MB" in lines[0], lines
    assert not (tmp_path / "out.spz").exists()
