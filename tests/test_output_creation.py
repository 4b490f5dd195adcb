"""Issue #43 item 5: a refused output creates nothing, no folder and no temporary file.

``convert``, ``apply`` and ``deform`` to an output in a folder that does not exist yet, in a
format only read here (``.ksplat``), exit 2 with one line and leave the tree as it was: the
writer's refusal comes after :func:`splatdeform.io.atomic.atomic_path` made the folder and the
temporary file, and both go again (any writer's late refusal does the same).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

import splatdeform as sd
from data_tools.synth import gaussian_bar
from splatdeform.cli import main
from tests.conftest import shared_file

HANDLE = """input: in.ply
output: out.ply
regions:
  units: relative
  fixed: [{box: {min: [0,0,0], max: [1,0.2,1]}}]
  handle: [{box: {min: [0,0.8,0], max: [1,1,1]}}]
handle:
  transform: {translate: [0.05, 0, 0]}
"""


def _tree(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def _one_line(capsys, *words: str) -> None:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err


@pytest.mark.parametrize("out", ["nd/out.ksplat", "nd/deeper/out.ksplat", "out.ksplat"])
def test_convert_to_a_read_only_format_creates_nothing(tmp_path, monkeypatch, capsys, out):
    monkeypatch.chdir(tmp_path)
    sd.save(gaussian_bar(200, seed=1), tmp_path / "x.ply")
    before = _tree(tmp_path)
    assert main(["convert", "x.ply", out]) == 2
    _one_line(capsys, "out.ksplat", "read only")
    assert _tree(tmp_path) == before


@pytest.fixture(scope="module")
def field(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("field")
    shutil.copy(shared_file("scans/bunny_res2.ply"), root / "in.ply")
    (root / "e.yaml").write_text(HANDLE)
    assert main(["deform", str(root / "e.yaml"), "--save-field", str(root / "f.npz"),
                 "--quiet"]) == 0
    return root


def test_apply_to_a_read_only_format_creates_nothing(field, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    shutil.copy(field / "in.ply", tmp_path / "m.ply")
    before = _tree(tmp_path)
    assert main(["apply", str(field / "f.npz"), "m.ply", "-o", "new2/out.ksplat"]) == 2
    _one_line(capsys, "out.ksplat", "read only")
    assert _tree(tmp_path) == before


def test_deform_to_a_read_only_format_creates_nothing(field, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    shutil.copy(field / "in.ply", tmp_path / "in.ply")
    (tmp_path / "e.yaml").write_text(HANDLE)
    before = _tree(tmp_path)
    assert main(["deform", "e.yaml", "-o", "new3/sub/out.ksplat", "--quiet"]) == 2
    _one_line(capsys, "out.ksplat", "read only")
    assert _tree(tmp_path) == before


BATCH = """scans: scans
output_dir: ro
edit:
  regions:
    units: relative
    fixed: [{box: {min: [0,0,0], max: [0.2,1,1]}}]
    handle: [{box: {min: [0.8,0,0], max: [1,1,1]}}]
  handle:
    transform: {translate: [0.05, 0, 0]}
"""


def test_batch_into_a_read_only_folder_names_the_report(tmp_path, monkeypatch, capsys):
    """The report that cannot be written is named by its own path, never by the temporary
    file beside it (a read-only tmpfs as root, which ignores permission bits; else 0555)."""
    import os
    import subprocess

    from data_tools.synth import bumpy_bar

    monkeypatch.chdir(tmp_path)
    (tmp_path / "scans").mkdir()
    sd.save(bumpy_bar(300, seed=1), tmp_path / "scans" / "a.ply")
    (tmp_path / "b.yaml").write_text(BATCH)
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() == 0:
        res = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(ro)],
                             capture_output=True, text=True)
        if res.returncode != 0:
            pytest.skip(f"cannot mount a read-only tmpfs: {res.stderr.strip()}")
    else:
        ro.chmod(0o555)
    try:
        assert main(["batch", "b.yaml", "--workers", "1"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err and f"{ro / 'report.json'}:" in err[-1], err
        assert ".tmp" not in err[-1], err
        assert list(ro.iterdir()) == []
    finally:
        if os.geteuid() == 0:
            subprocess.run(["umount", str(ro)], check=False)
        else:
            ro.chmod(0o755)
