"""Shared by the editor's pair tests (tests/test_editor_pairs*.py): a ``points:`` edit beside a
copy of the bar, and ``deform`` run again on a saved YAML (byte for byte)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import yaml

GCP = ("x,y,z,X,Y,Z\n3.5,0,0,3.5,0.3,0.1\n4.5,0.2,0,4.6,0.5,0\n"
       "2.5,-0.2,0.1,2.5,0,0.2\n4,0,-0.1,4,0.2,0\n")


def points_edit(folder: Path, bar: Path, extra: str = "") -> Path:
    """pts.yaml beside a copy of ``bar``: a fixed box and the 4 pairs of gcp.csv (``extra``:
    more lines of the ``points:`` mapping)."""
    shutil.copy(bar, folder / "bar.ply")
    (folder / "gcp.csv").write_text(GCP)
    path = folder / "pts.yaml"
    path.write_text("input: bar.ply\noutput: pts_out.ply\nfit: {tolerance: 0.001}\n"
                    "regions:\n  fixed: [{box: {min: [-1,-1,-1], max: [1,1,1]}}]\n"
                    "points:\n  pairs: {file: gcp.csv}\n" + extra)
    return path


def deform_again(work: Path, saved_yaml: str, saved_model: str) -> None:
    """``deform`` on the saved YAML (output renamed) writes the saved model's bytes."""
    data = yaml.safe_load((work / saved_yaml).read_text())
    data["output"] = "again.ply"
    (work / "again.yaml").write_text(yaml.safe_dump(data))
    run = subprocess.run([sys.executable, "-m", "splatdeform.cli", "deform", "again.yaml"],
                         cwd=work, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert (work / "again.ply").read_bytes() == (work / saved_model).read_bytes()
