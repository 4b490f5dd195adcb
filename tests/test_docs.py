"""The docs (issue 39): the generated reference pages match the code, every CLI flag and config
key is on them, the site builds with ``mkdocs build --strict``, the public API's examples run as
doctests on generated data, and the README's quick start runs as written."""

from __future__ import annotations

import doctest
import importlib
import os
import re
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from data_tools import docs_gen

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
BIN = Path(sys.executable).parent


def test_generated_pages_are_up_to_date():
    """docs/reference/*.md are what data_tools.docs_gen makes of the code now."""
    stale = [str(p.relative_to(ROOT)) for p, text in docs_gen.generate(DOCS).items()
             if not p.is_file() or p.read_text() != text]
    assert not stale, f"run `python -m data_tools.docs_gen` (or make docs): {stale} are stale"


def _sections(page: str) -> dict[str, str]:
    parts = re.split(r"^## ", page, flags=re.M)
    return {p.split("\n", 1)[0].strip(): p for p in parts[1:]}


def test_every_cli_flag_is_in_the_reference():
    sections = _sections((DOCS / "reference" / "cli.md").read_text())
    flags = docs_gen.cli_flags()
    assert set(flags) == set(sections), "every verb has its section"
    missing = [f"{verb} {flag}" for verb, names in flags.items() for flag in names
               if f"`{flag}" not in sections[verb]]
    assert not missing, f"not in docs/reference/cli.md: {missing}"


@pytest.mark.parametrize("page,root", [("edit-config.md", "splatdeform.edit.config:EditConfig"),
                                       ("batch-config.md", "splatdeform.batch.config:BatchConfig")])
def test_every_config_key_is_in_the_reference(page, root):
    module, name = root.split(":")
    model = getattr(importlib.import_module(module), name)
    text = (DOCS / "reference" / page).read_text()
    missing = []
    for sub, _ in docs_gen.walk(model, ""):
        section = text.split(f"{{#{docs_gen.anchor(sub)}}}", 1)
        assert len(section) == 2, f"{sub.__name__} has no section in {page}"
        body = section[1].split("\n## ", 1)[0]
        missing += [f"{sub.__name__}.{key}" for key in sorted({f.alias or n for n, f in
                                                              sub.model_fields.items()})
                    if f"| `{key}` |" not in body]
    assert not missing, f"keys not in docs/reference/{page}: {missing}"


@pytest.mark.slow
def test_docs_build_strict(tmp_path):
    """`mkdocs build --strict` (what `make docs` runs): any warning — a broken link, a missing
    page, an API object mkdocstrings cannot find — fails."""
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    run = subprocess.run([str(BIN / "mkdocs"), "build", "--strict", "--quiet", "-d",
                          str(tmp_path / "site")], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr
    assert (tmp_path / "site" / "api.html").is_file()


# The public API whose docstrings carry an Examples section, each run as a doctest (on models
# from data_tools.synth, never ../shared).
DOCTESTED = [
    "splatdeform.io:load", "splatdeform.io:save",
    "splatdeform.edit.run:run_edit", "splatdeform.edit.config:load_edit",
    "splatdeform.conversion:convert",
    "splatdeform.edit.selectors.box:Box", "splatdeform.edit.selectors.sphere:Sphere",
    "splatdeform.edit.selectors.plane:Plane", "splatdeform.edit.selectors.indices:Indices",
    "splatdeform.edit.selectors.prop:Property",
    "splatdeform.deform.deformation:prepare_handle", "splatdeform.deform.deformation:Deformation",
    "splatdeform.deform.model_apply:apply", "splatdeform.field:Field",
    "splatdeform.editor.controller:EditorController",
    "splatdeform.deform.handle:compose_transform", "splatdeform.deform.deformation:delta_for",
    "splatdeform.deform.handle:delta_for_transform",
    "splatdeform.deform.normals:estimate_normals", "splatdeform.deform.model_apply:full_basis",
    "splatdeform.deform.deformation:prepare_handles",
    "splatdeform.deform.deformation:prepare_metaphors", "splatdeform.edit.selectors:select",
    "splatdeform.model:PointModel",
]


def test_every_public_name_is_doctested_and_on_the_api_page():
    """Each function or class in ``splatdeform.__all__`` (the errors aside) has its example in
    DOCTESTED and its ``:::`` entry on docs/api.md."""
    import splatdeform

    targets = {id(getattr(importlib.import_module(t.split(":")[0]), t.split(":")[1])): t
               for t in DOCTESTED}
    public = {name: getattr(splatdeform, name) for name in splatdeform.__all__}
    public = {name: obj for name, obj in public.items()
              if not (isinstance(obj, type) and issubclass(obj, BaseException))}
    missing = sorted(name for name, obj in public.items() if id(obj) not in targets)
    assert not missing, f"public names with no doctested example (add to DOCTESTED): {missing}"
    api = (DOCS / "api.md").read_text()
    unlisted = [targets[id(obj)] for obj in public.values()
                if f"::: {targets[id(obj)].replace(':', '.')}\n" not in api]
    assert not unlisted, f"no mkdocstrings entry on docs/api.md: {unlisted}"


@pytest.mark.parametrize("target", DOCTESTED)
def test_api_examples_run(target, tmp_path, monkeypatch):
    module, name = target.split(":")
    obj = getattr(importlib.import_module(module), name)
    doc = obj.__doc__ or ""
    assert "Examples\n" in doc and ">>>" in doc, f"{target}: no numpydoc Examples section"
    assert "shared" not in doc, f"{target}: examples run on generated data, never ../shared"
    monkeypatch.chdir(tmp_path)   # examples write their files into the working folder
    finder = doctest.DocTestFinder(recurse=False)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    for test in finder.find(obj, name, globs={}):
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.attempted > 0 and result.failed == 0, f"{target}: {result}"


def _blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", text, flags=re.S)


def _fresh_venv_with_wheel(tmp_path: Path) -> Path:
    """A new virtual environment outside the clone with the wheel built from this tree
    installed; returns its bin folder. The dependencies come from this environment's
    site-packages through a .pth line (a plain path entry: its own .pth files, the editable
    install's among them, are not read), so nothing is downloaded and the clone is not on
    sys.path: only what the wheel ships can be imported as splatdeform."""
    import sysconfig

    # offline: hatchling (a dev dependency) builds it in this environment
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q",
                            "--no-build-isolation", "-w", str(tmp_path / "wheel"), str(ROOT)],
                           capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout + build.stderr
    (wheel,) = (tmp_path / "wheel").glob("splatdeform-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                   timeout=120)
    fresh = venv / "bin" / "python"
    site = subprocess.run([fresh, "-c", "import sysconfig; print(sysconfig.get_paths()"
                           "['purelib'])"], capture_output=True, text=True, check=True).stdout
    ours = {sysconfig.get_paths()[k] for k in ("purelib", "platlib")}
    (Path(site.strip()) / "_project_deps.pth").write_text("".join(f"{p}\n" for p in ours))
    proc = subprocess.run([sys.executable, "-m", "pip", "--python", str(fresh), "install",
                           "--no-deps", "--no-index", "-q", str(wheel)],
                          capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return venv / "bin"


@pytest.mark.slow
def test_readme_quick_start_runs_as_written(tmp_path):
    """The README's quick start from the wheel installed in a fresh venv, run in a folder
    outside the clone (issue 48): its bash lines run in order (`splatdeform` from that venv's
    bin, no PYTHONPATH); `splatdeform example bar` writes exactly the bend.yaml the README
    shows, and the Python snippet runs too; the `edit` step is started, its page fetched with
    the printed token, then stopped with SIGTERM (exit 0)."""
    readme = (ROOT / "README.md").read_text()
    quick = readme.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    bin_dir = _fresh_venv_with_wheel(tmp_path)
    work = tmp_path / "work"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = f"{bin_dir}{os.pathsep}{os.environ['PATH']}"
    where = subprocess.run(["python", "-c", "import splatdeform, importlib.util; "
                            "print(splatdeform.__file__, importlib.util.find_spec('data_tools'))"],
                           cwd=work, env=env, capture_output=True, text=True, timeout=120)
    assert where.returncode == 0, where.stderr
    assert where.stdout.startswith(str(bin_dir.parent)) and where.stdout.split()[1] == "None"
    version = subprocess.run(["splatdeform", "--version"], cwd=work, env=env,
                             capture_output=True, text=True, timeout=120)
    assert version.stdout.strip() == "splatdeform 0.1.0", version.stdout + version.stderr
    lines = [ln.split("#", 1)[0].strip() for block in _blocks(quick, "bash")
             for ln in block.splitlines()]
    lines = [ln for ln in lines if ln]
    assert [ln.split()[1] for ln in lines if ln.startswith("splatdeform")] == \
        ["example", "select", "deform", "render", "edit"]
    for line in lines:
        if line.startswith("splatdeform edit"):
            continue
        run = subprocess.run(line, shell=True, cwd=work, env=env, capture_output=True,
                             text=True, timeout=300)
        assert run.returncode == 0, f"{line}: {run.stdout}{run.stderr}"
        if line.startswith("splatdeform example"):
            assert (work / "bend.yaml").read_text() == _blocks(quick, "yaml")[0]
    assert (work / "out" / "bar_bent.ply").is_file()
    assert (work / "out" / "before_after.png").is_file()
    snippet = subprocess.run(["python", "-c", _blocks(quick, "python")[0]], cwd=work, env=env,
                             capture_output=True, text=True, timeout=300)
    assert snippet.returncode == 0, snippet.stderr
    centers, converged = snippet.stdout.split()
    assert int(centers) > 0 and converged == "True"

    edit = next(ln for ln in lines if ln.startswith("splatdeform edit"))
    proc = subprocess.Popen(edit.split() + ["--port", "0"], cwd=work, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url = None
        for _ in range(200):
            line = proc.stdout.readline()
            if not line:
                break
            found = re.search(r"http://\S+/\?t=\S+", line)
            if found:
                url = found.group(0)
                break
        assert url, "the editor printed no URL with a token"
        with urllib.request.urlopen(url, timeout=30) as page:
            assert page.status == 200
            assert b"<html" in page.read(4096).lower()
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=30)
    assert code == 0
