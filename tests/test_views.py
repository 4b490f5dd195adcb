"""Views that read on the first try (issue 35): the default camera fills the picture with the
model's robust projected extent (flat scenes seen obliquely, z-up for LiDAR and geo-referenced
scans), --zoom narrows it, camera files without near/far draw the model, a camera that draws
nothing says so, ``info`` prints the up axis, ``select -o`` shows the regions. Real renders on
the EGL context."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import bar_edit, egl_renderer, shared_file
from helpers import run_cli
from PIL import Image

import splatdeform as sd
from splatdeform.model import PointModel
from splatdeform.render.camera import View, load_camera
from splatdeform.render.compare import LABEL_HEIGHT, render_comparison
from splatdeform.render.framing import FLAT_ELEVATION, FramingNote, is_flat
from splatdeform.render.upaxis import up_rule
from splatdeform.render.visibility import BlankRenderWarning


@pytest.fixture(scope="module", autouse=True)
def _egl():
    egl_renderer((16, 16)).release()   # a missing EGL device fails loudly, once


def _drawn_box(path: Path) -> tuple[float, float, float]:
    """(width span, height span, area) of the bounding box of the non-background pixels of a
    one-panel image, as fractions of the panel (the label strip left out)."""
    image = np.asarray(Image.open(path).convert("RGB")).astype(int)[LABEL_HEIGHT:]
    ys, xs = np.nonzero(np.abs(image - 255).max(axis=2) > 8)
    h, w = image.shape[:2]
    sw, sh = (xs.max() - xs.min() + 1) / w, (ys.max() - ys.min() + 1) / h
    return sw, sh, sw * sh


@pytest.mark.parametrize("name", ["lidar/simple.laz", "scans/lidar_terrain_522k.ply"])
def test_flat_geo_scenes_fill_the_default_frame_z_up(name, tmp_path):
    model = sd.load(shared_file(name))
    assert up_rule([model])[0] == "+z" and is_flat(model.positions, "+z")
    out = tmp_path / "view.png"
    render_comparison(model, None, out, View(size=(1200, 600)), labels=("x",))  # render's size
    sw, sh, area = _drawn_box(out)
    assert max(sw, sh) >= 0.70 and area >= 0.35, (sw, sh, area)
    cam = json.loads(out.with_name("view.camera.json").read_text())
    assert cam["up"][2] > 0.5                                   # z-up on screen
    forward = np.subtract(cam["target"], cam["position"])
    elevation = math.degrees(math.asin(-forward[2] / np.linalg.norm(forward)))
    assert elevation == pytest.approx(FLAT_ELEVATION, abs=0.5)  # oblique: flat scene
    lo, hi = model.bbox()
    assert cam["near"] > 0 and cam["far"] > cam["near"]


def test_up_rule_on_the_shared_files_and_info_prints_it(tmp_path):
    ups = {name: up_rule([sd.load(shared_file(name))])[0]
           for name in ("lidar/simple.laz", "scans/lidar_terrain_522k.ply", "scans/bunny.ply",
                        "splats/tile_3dgs_sh3.ply")}
    assert ups == {"lidar/simple.laz": "+z", "scans/lidar_terrain_522k.ply": "+z",
                   "scans/bunny.ply": "+y", "splats/tile_3dgs_sh3.ply": "-y"}
    # a CRS comment makes a small-coordinate scan geo-referenced too
    path = tmp_path / "crs.ply"
    path.write_text("ply\nformat ascii 1.0\ncomment crs EPSG:32633\nelement vertex 3\n"
                    "property float x\nproperty float y\nproperty float z\nend_header\n"
                    "0 0 0\n1 0 0\n0 1 0.1\n")
    model = sd.load(path)
    assert up_rule([model])[0] == "+z"
    res = run_cli("info", path)
    assert res.returncode == 0, res.stderr
    assert "up:       +z (geo-referenced: a CRS comment" in res.stdout
    res = run_cli("info", shared_file("scans/lidar_terrain_522k.ply"))
    assert "up:       +z (geo-referenced: horizontal coordinates beyond 1e5" in res.stdout


def _camera_file(path: Path, model: PointModel, offset, *, target=None, clip=None) -> Path:
    lo, hi = model.bbox()
    centre = (lo + hi) / 2
    data = {"position": (centre + np.asarray(offset)).tolist(),
            "target": (centre if target is None else np.asarray(target)).tolist(),
            "up": [0.0, 1.0, 0.0], "fov_y_degrees": 35.0, "width": 200, "height": 200}
    if clip:
        data.update(near=clip[0], far=clip[1])
    path.write_text(json.dumps(data))
    return path


def test_hand_written_camera_without_near_far_draws_the_model(tmp_path):
    bunny = sd.load(shared_file("scans/bunny.ply"))
    cam = _camera_file(tmp_path / "hand.json", bunny, [0.0, 0.0, 0.4])
    view = View().with_options(camera_file=cam)
    assert view.camera.near is None and view.size == (200, 200)
    out = tmp_path / "hand.png"
    render_comparison(bunny, None, out, view, labels=("x",))
    sw, sh, _ = _drawn_box(out)
    assert min(sw, sh) > 0.2
    written, size = load_camera(tmp_path / "hand.camera.json")   # completed: re-renders as is
    depth = written.position[2] - bunny.positions[:, 2]        # looking down -z
    assert written.near < depth.min() and written.far > depth.max() and size == (200, 200)
    np.testing.assert_array_equal(written.position, view.camera.position)  # used as written


def test_a_camera_looking_away_warns_naming_it(tmp_path):
    bunny = sd.load(shared_file("scans/bunny.ply"))
    lo, hi = bunny.bbox()
    centre = (lo + hi) / 2
    away = _camera_file(tmp_path / "away.json", bunny, [0.0, 0.0, 0.4],
                        target=centre + [0.0, 0.0, 1.0], clip=(0.01, 10.0))
    with pytest.warns(BlankRenderWarning) as caught:
        render_comparison(bunny, None, tmp_path / "away.png",
                          View().with_options(camera_file=away), labels=("x",))
    line = str(caught[0].message)
    assert str(away) in line and "near 0.01, far 10" in line and "behind the camera" in line
    assert "\n" not in line
    # through the CLI: exit 0, the picture, and one warning line
    res = run_cli("render", shared_file("scans/bunny.ply"), "-o", tmp_path / "cli.png",
                  "--camera", away)
    assert res.returncode == 0, res.stderr
    warnings = [ln for ln in res.stderr.splitlines() if "warning" in ln]
    assert len(warnings) == 1 and "away.json" in warnings[0] and "far 10" in warnings[0]


def test_zoom_narrows_the_view_fov_is_the_lens_angle(tmp_path):
    bunny = sd.load(shared_file("scans/bunny.ply"))
    a = render_comparison(bunny, None, tmp_path / "a.png", View(size=(160, 160)), labels=("x",))
    render_comparison(bunny, None, tmp_path / "z.png", View(size=(160, 160), zoom=2.0),
                      labels=("x",))
    ca, _ = load_camera(tmp_path / "a.camera.json")
    cz, _ = load_camera(tmp_path / "z.camera.json")
    np.testing.assert_allclose(cz.position, ca.position)
    assert math.tan(math.radians(cz.fov / 2)) == pytest.approx(
        math.tan(math.radians(ca.fov / 2)) / 2)
    # a narrower lens still fills the picture (the framing moves the camera back)
    narrow = render_comparison(bunny, None, tmp_path / "n.png", View(size=(160, 160), fov=15),
                               labels=("x",))
    assert narrow.shape == a.shape
    assert max(_drawn_box(tmp_path / "n.png")[:2]) >= 0.85
    assert max(_drawn_box(tmp_path / "a.png")[:2]) >= 0.85
    with pytest.raises(sd.InputError, match="--zoom"):
        View().with_options(zoom=0)


def test_floaters_do_not_shrink_the_subject_and_are_reported(tmp_path):
    rng = np.random.default_rng(3)
    grid = rng.uniform(0, 1, (20000, 3)) * [1.0, 1.0, 1.0]
    floaters = rng.uniform(-1, 1, (20, 3)) * 40.0
    model = PointModel(positions=np.concatenate([grid, floaters]),
                       normals=None, colors=None, path="floaters.ply")
    with pytest.warns(FramingNote, match="outliers outside the picture"):
        render_comparison(model, None, tmp_path / "f.png", View(size=(200, 200)), labels=("x",))
    cam, _ = load_camera(tmp_path / "f.camera.json")
    assert np.linalg.norm(cam.position - np.array([0.5, 0.5, 0.5])) < 6.0   # framed on the cube


def test_select_preview_colours_regions_even_with_render_color(tmp_path):
    from data_tools.synth import bumpy_bar
    from splatdeform.edit.selection import FIXED_COLOR, MOVING_COLOR

    sd.save(bumpy_bar(3000, seed=2), tmp_path / "bar.ply")
    cfg = bar_edit(input="bar.ply", output="out.ply", render={"color": "elevation"})
    (tmp_path / "e.yaml").write_text(yaml.safe_dump(cfg))
    res = run_cli("select", tmp_path / "e.yaml", "-o", tmp_path / "p.png")
    assert res.returncode == 0, res.stderr
    image = np.asarray(Image.open(tmp_path / "p.png").convert("RGB")).astype(int)

    def share(color) -> float:
        return float((np.abs(image - np.array(color)).max(axis=2) < 40).mean())

    assert share(FIXED_COLOR) > 0.005 and share(MOVING_COLOR) > 0.005
    res = run_cli("select", tmp_path / "e.yaml", "-o", tmp_path / "q.png", "--color", "elevation")
    assert res.returncode == 0, res.stderr
    image = np.asarray(Image.open(tmp_path / "q.png").convert("RGB")).astype(int)
    assert share(MOVING_COLOR) < 0.002
