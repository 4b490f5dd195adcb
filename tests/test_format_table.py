"""The format table (issue 33 item 1): every format declares itself once in
:mod:`splatdeform.io.declare`, and ``splatdeform.io`` merges the declarations.

- every declared extension loads and saves a small generated model where the format writes;
- each format's header probe counts what the loader loads (the splat formats from the count
  their header declares);
- no extension is compared outside ``splatdeform/io/`` but through its one case-insensitive
  parser (:func:`splatdeform.io.extension_of` / ``split_extension``): an AST check that sees
  ``.suffix`` comparisons, ``.endswith`` and comparisons with extension strings;
- batch derives ``x_deformed.compressed.ply`` (same format) from ``x.compressed.ply``;
- an SPZ that declares 10M splats in 1 MB is refused by ``deform --memory-budget 200MB`` from
  its declared count (one line naming the estimate and the budget).
"""

from __future__ import annotations

import ast
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
from splatdeform.errors import FormatError
from splatdeform.io import FORMATS, SOG_META, extension_of, split_extension

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "splatdeform"
SPLAT_KEYS = [ext for ext, fmt in FORMATS.items() if fmt.lossy or fmt.module == "gltf"]
POINT_KEYS = [ext for ext in FORMATS if ext not in SPLAT_KEYS]
READ_ONLY = {".ksplat"}


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
                              ".glb", ".gltf", ".pcd", ".xyz", ".xyzn", ".pts", ".las", ".laz",
                              ".e57")
    assert sd.io.LIDAR_EXTENSIONS == (".las", ".laz", ".e57")
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
    SPZ declaring 3M splats is estimated from 3M (the probe reads only its header); 10M, more
    than its compressed bytes plausibly hold (64x + 16 MiB), is refused by the probe."""
    path = tmp_path / "big.spz"
    path.write_bytes(_declaring_spz(3_000_000))
    assert path.stat().st_size < 1.2 * 2**20
    cost = memory.file_cost(path)
    assert cost.points == 3_000_000
    assert cost.load_bytes > 3_000_000 * 20
    path.write_bytes(_declaring_spz(10_000_000))
    with pytest.raises(FormatError, match="10,000,000 splats .* compresses at most 64x"):
        memory.file_cost(path)


# --------------------------------------------------------------------------------------------
# no extension compared outside splatdeform/io/ but through io's one parser

#: comparisons of file types that are not model formats, by (module, function): why. Each is
#: case-insensitive (``.lower()``) unless it names the project's own files.
NOT_FORMATS = {
    ("editor/controller.py", "EditorController.open"): "an edit file (YAML) or a model",
    ("editor/saving.py", "_save"): "an edit file (YAML) and an image (editor save)",
    ("editor/page_server.py", "_Handler._static"): "the page's own web assets (MIME types)",
    ("edit/images.py", "render_target"): "an image output",
    ("edit/config.py", "check_render_output"): "an image or GIF output (render config)",
    ("render/frames.py", "render_frames"): "a GIF output",
    ("verbs.py", "cmd_select"): "a PNG preview output",
    ("verbs.py", "cmd_render"): "a PNG output",
}
#: comparisons to move onto ``splatdeform.io.extension_of`` (owned elsewhere), by (module,
#: function): why; remove an entry when it is fixed
PENDING: dict[tuple[str, str], str] = {}
#: an extension as a string: ``.ply``, ``.compressed.ply``, ``.tar.gz``
EXTENSION = re.compile(r"^\.[a-z0-9]+(\.[a-z0-9]+)*$", re.IGNORECASE)
PARSERS = {"extension_of", "split_extension"}


def _strings(node: ast.AST, consts: dict[str, list[str]]) -> list[str]:
    """The string literals ``node`` is or holds (a tuple, list or set; a module constant)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return [node.value]
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return [s for e in node.elts for s in _strings(e, consts)]
    if isinstance(node, ast.Name):
        return consts.get(node.id, [])
    return []


def _names_extension(node: ast.AST, consts: dict[str, list[str]]) -> bool:
    return any(EXTENSION.match(s) for s in _strings(node, consts))


def _calls(node: ast.AST, names: set[str]) -> bool:
    return any(isinstance(n, ast.Call) and
               (getattr(n.func, "id", None) or getattr(n.func, "attr", None)) in names
               for n in ast.walk(node))


def _raw_extension(node: ast.AST) -> bool:
    """Whether ``node`` reads an extension without io's parser (``.suffix``, ``splitext``)."""
    return any(isinstance(n, ast.Attribute) and n.attr in ("suffix", "suffixes")
               for n in ast.walk(node)) or _calls(node, {"splitext"})


def extension_decisions(tree: ast.Module) -> list[tuple[str, int]]:
    """(function qualname, line) of each extension comparison in a module that does not go
    through :data:`PARSERS`: a comparison of a ``.suffix`` (or a name bound to one), a string
    comparison with an extension literal whose other side is not a parser's result, and an
    ``.endswith`` of an extension."""
    consts = {t.id: _strings(st.value, {}) for st in tree.body if isinstance(st, ast.Assign)
              for t in st.targets if isinstance(t, ast.Name) and _strings(st.value, {})}
    scopes: list[tuple[str, ast.AST]] = [("<module>", tree)]

    def nest(prefix: str, node: ast.AST) -> None:  # classes and functions by qualname
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                scopes.append((prefix + child.name, child))
                nest(prefix + child.name + ".", child)
            else:
                nest(prefix, child)

    nest("", tree)
    found = []
    for scope_name, scope in scopes:
        own = [n for n in ast.walk(scope) if _scope_of(n, scopes) is scope]
        parsed, raw = set(), set()
        for node in own:
            if isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None:
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                names = {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
                if _calls(node.value, PARSERS):
                    parsed |= names
                elif _raw_extension(node.value):
                    raw |= names
        for node in own:
            if isinstance(node, ast.Compare):
                sides = [node.left, *node.comparators]
                if any(_raw_extension(s) or (isinstance(s, ast.Name) and s.id in raw)
                       for s in sides) or (
                        any(_names_extension(s, consts) for s in sides) and
                        not any(_calls(s, PARSERS) or
                                (isinstance(s, ast.Name) and s.id in parsed) for s in sides)):
                    found.append((scope_name, node.lineno))
            elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                    node.func.attr in ("endswith", "removesuffix") and \
                    any(_names_extension(a, consts) for a in node.args):
                found.append((scope_name, node.lineno))
    return found


def _scope_of(node: ast.AST, scopes: list[tuple[str, ast.AST]]) -> ast.AST:
    """The innermost of ``scopes`` holding ``node`` (by line span)."""
    best = scopes[0][1]
    for _, scope in scopes[1:]:
        if scope is not node and scope.lineno <= getattr(node, "lineno", 0) <= \
                scope.end_lineno and scope.lineno >= getattr(best, "lineno", 0):
            best = scope
    return best


def extension_uses() -> dict[tuple[str, str], list[int]]:
    """(module, function) -> lines of each extension comparison outside io/ (by AST)."""
    found: dict[tuple[str, str], list[int]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel.startswith("io/"):
            continue
        for scope, line in extension_decisions(ast.parse(path.read_text(), str(path))):
            found.setdefault((rel, scope), []).append(line)
    return found


def test_no_extension_compared_outside_io():
    uses = extension_uses()
    unknown = sorted((key, uses[key]) for key in uses.keys() - NOT_FORMATS.keys()
                     - PENDING.keys())
    assert not unknown, ("an extension compared outside splatdeform/io/ without its parser "
                         f"(use splatdeform.io.extension_of / split_extension): {unknown}")


def test_the_extension_scan_sees_what_it_must():
    """The scan sees each way of comparing an extension (and passes the parser's results);
    the allow-lists name functions that still compare one (a stale entry would hide a new
    use)."""
    source = """
ARCHIVES = (".zip", ".tar.gz")
def suffix(p): return p.suffix == ".ply"
def lowered(p): return p.suffix.lower() in (".yaml", ".yml")
def bound(p):
    s = Path(p).suffix.lower()
    return s not in allowed
def ends(p): return str(p).lower().endswith(".zip")
def ends_const(p): return p.endswith(ARCHIVES)
def literal(name): return name[-4:] == ".png"
def split(p): return os.path.splitext(p)[1] == ".las"
class C:
    def method(self, p): return p.name.endswith((".las", ".laz"))
def parsed(p): return extension_of(p) == ".ply"
def parsed_name(p):
    ext = extension_of(p)
    return ext in ARCHIVES
def parsed_pair(p):
    stem, ext = split_extension(p)
    return ext == ".gz"
def other(data, line): return data.endswith(b"\\n") or line.endswith(":") or line == "x"
"""
    found = {scope for scope, _ in extension_decisions(ast.parse(source))}
    assert found == {"suffix", "lowered", "bound", "ends", "ends_const", "literal", "split",
                     "C.method"}, found
    uses = extension_uses()
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
    spz_path.write_bytes(_declaring_spz(3_000_000))   # within what 1 MB plausibly holds
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
