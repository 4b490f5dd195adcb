"""What the CLI says and draws (issue 22), through the real command on a generated bar:

- ``select -o`` of a curve edit works when ``render:`` has no ``output`` and draws the curve
  before (red) and after (green) and its snapped control points over the region preview;
- ``deform --quiet`` prints nothing on stdout (and writes its output); ``deform --render`` says
  where the image went;
- a before/after of two different models frames each panel on its own model; one model before
  and after an edit keeps one camera.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import helpers
import numpy as np
import pytest
import yaml
from conftest import egl_renderer
from PIL import Image

import splatdeform as sd
from data_tools.synth import bumpy_bar, sphere
from splatdeform.edit.metaphors.curve import CURVE_AFTER_COLOR, CURVE_BEFORE_COLOR
from splatdeform.render.camera import View
from splatdeform.render.compare import render_comparison


def run_cli(*args) -> subprocess.CompletedProcess:
    return helpers.run_cli(*args, timeout=300)


@pytest.fixture(scope="module")
def curve_config(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cli_output")
    sd.save(bumpy_bar(4000, seed=5), root / "bar.ply")
    cfg = {
        "input": "bar.ply", "output": "bent.ply",
        "regions": {"units": "model",
                    "fixed": [{"box": {"min": [-1, -1, -1], "max": [0.6, 1, 1]}},
                              {"box": {"min": [3.4, -1, -1], "max": [5, 1, 1]}}]},
        "curve": {"control_points": [[1.2, 0.5, 0], [1.7, 0.5, 0], [2.3, 0.5, 0], [2.8, 0.5, 0]],
                  "moved_to": [[1.2, 0.5, 0], [1.7, 0.85, 0], [2.3, 0.85, 0], [2.8, 0.5, 0]],
                  "capture_radius": 0.12},
        "fit": {"tolerance": 2e-3, "max_centers": 1000},
        "backend": "numpy",
        "render": {"size": [600, 300], "azimuth": 0, "elevation": 10},  # no output
    }
    path = root / "curve.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def count_color(image: np.ndarray, color) -> int:
    return int((np.abs(image.astype(int) - np.array(color)).max(axis=2) <= 10).sum())


def test_select_draws_the_curve_without_render_output(curve_config):
    out = curve_config.parent / "select.png"
    res = run_cli("select", curve_config, "-o", out)
    assert res.returncode == 0, res.stderr
    image = np.asarray(Image.open(out).convert("RGB"))
    assert count_color(image, CURVE_BEFORE_COLOR) > 100
    assert count_color(image, CURVE_AFTER_COLOR) > 100
    assert count_color(image, (20, 20, 20)) > 20  # control point dots


def test_deform_quiet_and_render_path(curve_config):
    out = curve_config.parent / "bent_quiet.ply"
    res = run_cli("deform", curve_config, "-o", out, "--quiet")
    assert res.returncode == 0, res.stderr
    assert res.stdout == "" and out.is_file()
    image = curve_config.parent / "bent.png"
    res = run_cli("deform", curve_config, "-o", out, "--render", image)
    assert res.returncode == 0, res.stderr
    assert f"rendered {image}" in res.stdout.splitlines() and image.is_file()


def filled_fraction(panel: np.ndarray) -> float:
    """Fraction of the panel's height covered by non-white pixels' bounding box."""
    rows = np.flatnonzero((panel < 245).any(axis=(1, 2)))
    return (rows[-1] - rows[0] + 1) / panel.shape[0] if rows.size else 0.0


def test_two_different_models_each_framed_on_their_own(tmp_path):
    egl_renderer((8, 8)).release()  # fail loudly without EGL
    small = sphere(3000, radius=0.1, seed=1)
    big = sphere(4000, radius=5.0, seed=2)
    big.positions += 20.0
    image = render_comparison(small, big, None, View(size=(200, 200)), labels=("a", "b"))
    left, right = image[18:, :200], image[18:, 200:]
    assert filled_fraction(left) > 0.4 and filled_fraction(right) > 0.4
    # the same scene before/after (same point count) keeps one camera: the small sphere
    # moved far away stays small in the second panel
    moved = sphere(3000, radius=0.1, seed=1)
    moved.positions += 20.0
    image = render_comparison(small, moved, None, View(size=(200, 200)), labels=("a", "b"))
    assert filled_fraction(image[18:, :200]) < 0.2
