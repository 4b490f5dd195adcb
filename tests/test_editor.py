"""The editor: controller (no browser), the ``edit`` verb in a subprocess (the page; loopback
only, Ctrl-C / SIGTERM end it with exit 0; the retired ``--viewer viser`` is an invalid choice
in one line), and one real headless chromium on the verb's page."""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import urllib.request
from pathlib import Path

import helpers
import numpy as np
import pytest
import yaml
from fixtures import start_editor

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.deform.handle import compose_transform
from splatdeform.edit.config import load_edit
from splatdeform.edit.run import run_edit
from splatdeform.edit.selectors import Box, Sphere, select
from splatdeform.editor import EditorController, StaleFitError
from splatdeform.errors import InputError, RegionError
from splatdeform.model import Gaussians

N = 2000
FIXED = Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
HANDLE = Box((3.0, -1.0, -1.0), (5.0, 1.0, 1.0))
POSE = compose_transform(pivot=np.array([3.5, 0.0, 0.0]), axis=(0, 0, 1), degrees=25,
                         translate=(0, 0.3, 0.1))


@pytest.fixture(scope="module")
def bar_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("editor") / "bar.ply"
    sd.save(bumpy_bar(N, seed=5), path)
    return path


@pytest.fixture()
def bar_copy(bar_path, tmp_path) -> Path:
    path = tmp_path / "bar.ply"
    shutil.copy(bar_path, path)
    return path


@pytest.fixture(scope="module")
def fitted(bar_path) -> EditorController:
    ed = EditorController.open(bar_path)
    ed.add_selector("fixed", FIXED)
    ed.add_selector("handle", HANDLE)
    ed.settings.fit.tolerance = 1e-3
    ed.fit()
    return ed


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return helpers.run_cli(*args, cwd=cwd or Path.cwd(), timeout=120)


# ---- controller --------------------------------------------------------------------------
def test_selector_edits_change_the_masks(bar_path):
    ed = EditorController.open(bar_path)
    assert ed.counts() == {"fixed": 0, "handle": 0, "free": N, "overlap": 0}
    ed.add_selector("fixed", FIXED)
    fixed0 = ed.masks()[0].copy()
    assert np.array_equal(fixed0, select(ed.model, [FIXED]))
    ed.move_selector("fixed", 0, center=(0.5, 0.0, 0.0))  # box 2 wide: now x in [-0.5, 1.5]
    moved = ed.masks()[0]
    assert np.array_equal(moved, select(ed.model, [Box((-0.5, -1, -1), (1.5, 1, 1))]))
    ed.resize_selector("fixed", 0, 1.5)
    assert (ed.masks()[0] >= moved).all() and ed.masks()[0].sum() > moved.sum()
    i = ed.add_selector("handle", "sphere", center=(4.0, 0.0, 0.0))
    shape = ed.shape("handle", i)
    assert shape.kind == "sphere" and np.allclose(shape.center, (4, 0, 0))
    handle = ed.masks()[1][0]
    dist = np.linalg.norm(ed.model.positions - (4, 0, 0), axis=1)
    assert np.array_equal(handle, dist <= shape.size[0])
    labels = ed.labels()
    assert set(np.unique(labels)) <= {0, 1, 2}
    assert (labels == 1).sum() == ed.counts()["fixed"] and (labels == 2).sum() == handle.sum()
    ed.remove_selector("handle", i)
    assert ed.counts()["handle"] == 0


def test_relative_units_from_yaml_keep_the_masks_of_deform(bar_path, tmp_path):
    cfg = {"input": str(bar_path), "output": str(tmp_path / "out.ply"),
           "regions": {"units": "relative",
                       "fixed": [{"box": {"min": [0, 0, 0], "max": [0.25, 1, 1]}}],
                       "handle": [{"sphere": {"center": [0.95, 0.5, 0.5], "radius": 0.15}}]},
           "handle": {"transform": {"pivot": "centroid", "translate": [0, 0.1, 0]}},
           "fit": {"tolerance": 1e-3}, "backend": "numpy"}
    path = tmp_path / "edit.yaml"
    path.write_text(yaml.safe_dump(cfg))
    ed = EditorController.from_config(path)
    parsed = load_edit(path)
    model = ed.model
    assert np.array_equal(ed.masks()[0], select(model, [s.to_selector() for s in
                                                        parsed.regions.fixed], "relative"))
    assert np.array_equal(ed.masks()[1][0], select(model, [s.to_selector() for s in
                                                           parsed.regions.handle], "relative"))
    # the pose of the YAML (translate 0.1 of the bbox height) became the handle matrix
    lo, hi = model.bbox()
    assert np.allclose(ed.handles[0].matrix[:3, 3], [0, 0.1 * (hi - lo)[1], 0])
    # a model-space move round trips through relative units
    shape = ed.shape("handle", 0)
    ed.move_selector("handle", 0, center=shape.center + (-0.2, 0, 0))
    assert np.allclose(ed.shape("handle", 0).center, shape.center + (-0.2, 0, 0))
    assert np.isclose(ed.shape("handle", 0).size[0], shape.size[0])


def test_fit_then_set_pose_equals_deform(bar_path, tmp_path):
    cfg = {"input": str(bar_path), "output": str(tmp_path / "out.ply"),
           "regions": {"fixed": [{"box": {"min": list(FIXED.min), "max": list(FIXED.max)}}],
                       "handle": [{"box": {"min": list(HANDLE.min), "max": list(HANDLE.max)}}]},
           "handle": {"transform": {"pivot": [3.5, 0, 0], "rotate": {"axis": [0, 1, 1],
                                                                      "degrees": 30},
                                    "translate": [0.1, 0.4, 0]}},
           "fit": {"tolerance": 1e-3}}
    path = tmp_path / "edit.yaml"
    path.write_text(yaml.safe_dump(cfg))
    ed = EditorController.from_config(path)
    ed.fit()
    frame = ed.set_pose(ed.handles[0].matrix)
    ref = run_edit(load_edit(path), tmp_path, save_output=False).deformed
    diag = ed.model.diagonal()
    assert np.abs(frame.positions + ed.origin - ref.positions).max() < 1e-5 * diag
    assert np.abs(frame.normals - ref.normals).max() < 1e-3
    fixed = ed.masks()[0]
    assert np.array_equal(frame.positions[fixed] + ed.origin.astype(np.float32),
                          (ed.model.positions[fixed] - ed.origin).astype(np.float32)
                          + ed.origin.astype(np.float32))
    # identity pose: nothing moves
    still = ed.set_pose(np.eye(4))
    assert np.abs(still.positions + ed.origin - ed.model.positions).max() < 1e-6 * diag


def test_saved_yaml_reproduces_the_saved_model_byte_for_byte(bar_copy):
    before = _digest(bar_copy)
    ed = EditorController.open(bar_copy)
    ed.add_selector("fixed", FIXED)
    ed.add_selector("handle", "box", center=(4.0, 0.0, 0.0))
    ed.move_selector("handle", 0, size=(1.2, 1.2, 1.2))
    ed.settings.fit.tolerance = 1e-3
    ed.fit()
    ed.set_pose(POSE)
    result = ed.save(image_size=(128, 128))
    folder = bar_copy.parent
    assert result.model == folder / "bar_edited.ply"
    assert result.config == folder / "bar_edit.yaml" and result.image == folder / "bar_edit.png"
    text = result.config.read_text()
    data = yaml.safe_load(text)
    # "auto" unless chosen: the YAML also runs on a machine without OpenCL
    assert data["backend"] == "auto" and len(data["handle"]["matrix"]) == 4
    assert data["input"] == "bar.ply" and data["output"] == "bar_edited.ply"
    run = _cli("deform", str(result.config), "-o", str(folder / "again.ply"))
    assert run.returncode == 0, run.stderr
    assert (folder / "again.ply").read_bytes() == result.model.read_bytes()
    assert _digest(bar_copy) == before
    from PIL import Image

    image = np.asarray(Image.open(result.image).convert("RGB")).astype(int)
    assert image.shape[1] == 128  # image_size is both panels, as render.size
    left, right = np.array_split(image[20:], 2, axis=1)
    assert image.std() > 5 and np.abs(left - right).sum() > 0
    assert not list(folder.glob(".*tmp*"))


def test_save_writes_the_image_deform_render_writes_for_the_yaml(bar_copy):
    """The editor's Save and ``deform --render`` on the saved YAML write the same PNG (pixels
    and bytes) and camera file: render.size, azimuth, elevation, fov, zoom, up, roll, color
    and a camera file (relative to the YAML) are all honoured."""
    import json
    import math

    from PIL import Image

    folder = bar_copy.parent
    render = {"size": [240, 120], "azimuth": 55.0, "elevation": 25.0, "fov": 30.0, "zoom": 1.7,
              "up": "+z", "roll": 8.0, "color": "elevation"}
    (folder / "e.yaml").write_text(yaml.safe_dump({
        "input": "bar.ply", "output": "out.ply", "backend": "numpy",
        "regions": {"fixed": [{"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}],
                    "handle": [{"box": {"min": [3, -1, -1], "max": [5, 1, 1]}}]},
        "handle": {"transform": {"pivot": [3.5, 0, 0], "rotate": {"axis": [0, 0, 1],
                                                                   "degrees": 25},
                                 "translate": [0, 0.3, 0.1]}},
        "fit": {"tolerance": 1e-3}, "render": render}))

    def both(ed: EditorController, tag: str) -> tuple[np.ndarray, dict]:
        where = folder / tag   # the saved YAML's paths are rewritten relative to its folder
        where.mkdir()
        saved = ed.save(model_path=where / "m.ply", config_path=where / "e.yaml",
                        image_path=where / "e.png")
        run = _cli("deform", str(saved.config), "-o", str(where / "cli.ply"),
                   "--render", str(where / "cli.png"), "--quiet")
        assert run.returncode == 0, run.stderr
        assert (where / "cli.png").read_bytes() == saved.image.read_bytes()
        cameras = [json.loads((where / f"{name}.camera.json").read_text())
                   for name in ("e", "cli")]
        assert cameras[0] == cameras[1]
        return np.asarray(Image.open(saved.image).convert("RGB")), cameras[0]

    ed = EditorController.from_config(folder / "e.yaml")
    ed.fit()
    image, camera = both(ed, "zoomed")
    assert image.shape[1] == 240 and image.std() > 5
    unzoomed = math.degrees(2 * math.atan(math.tan(math.radians(camera["fov_y_degrees"]) / 2)
                                          * 1.7))
    assert unzoomed == pytest.approx(30.0)   # render.zoom narrowed the 30-degree lens
    assert camera["up"][2] > 0.5   # render.up: +z
    # a camera file (relative to the YAML) wins over the view keys and brings the panel size
    cam = dict(camera, width=150, height=100, fov_y_degrees=40.0)
    (folder / "hand.camera.json").write_text(json.dumps(cam))
    ed.settings.render.camera = "hand.camera.json"
    image, camera = both(ed, "camera")
    assert image.shape[1] == 300 and camera["fov_y_degrees"] == 40.0


def test_two_handles_save_as_handles_and_reopen(bar_copy):
    ed = EditorController.open(bar_copy)
    ed.add_selector("fixed", Box((1.6, -1, -1), (2.4, 1, 1)))
    ed.add_selector("handle", Box((-1, -1, -1), (0.6, 1, 1)))
    second = ed.add_handle([Box((3.4, -1, -1), (5, 1, 1))])
    ed.settings.fit.tolerance = 1e-3
    stats = ed.fit()
    assert second == 1 and ed.deformation.k == 8 and stats["centers"] > 0
    ed.set_pose(compose_transform(pivot=np.zeros(3), translate=(0, 0.3, 0)), handle=0)
    frame = ed.set_pose(POSE, handle=1)
    assert frame.delta_c.shape == (8, 3)
    result = ed.save(image=False)
    data = yaml.safe_load(result.config.read_text())
    assert "handle" not in data and len(data["handles"]) == 2
    run = _cli("deform", str(result.config), "-o", str(bar_copy.parent / "again.ply"))
    assert run.returncode == 0, run.stderr
    again = (bar_copy.parent / "again.ply").read_bytes()
    assert again == result.model.read_bytes()
    moved = sd.load(result.model).positions
    assert np.abs(frame.positions + ed.origin - moved).max() < 1e-5 * ed.model.diagonal()
    back = EditorController.from_config(result.config)
    assert len(back.handles) == 2
    assert all(np.array_equal(a.matrix, b.matrix)
               for a, b in zip(back.handles, ed.handles, strict=True))
    assert back.to_yaml_dict() == ed.to_yaml_dict()


def test_stale_fit_is_detected(fitted):
    ed = fitted
    assert not ed.stale
    ed.set_pose(POSE)
    original = ed.fixed[0]
    ed.move_selector("fixed", 0, center=(-0.1, 0, 0))
    assert ed.stale
    with pytest.raises(StaleFitError, match="fit again"):
        ed.set_pose(POSE)
    with pytest.raises(StaleFitError):
        ed.deformed_model()
    ed.set_selector("fixed", 0, original)
    assert not ed.stale
    ed.settings.boundary.continuity = 1
    assert ed.stale
    ed.settings.boundary.continuity = 2
    assert not ed.stale


@pytest.mark.parametrize("name,fixed,handle,needle", [
    ("overlap", Box((-1, -1, -1), (3.5, 1, 1)), HANDLE, "overlap"),
    ("no_free_region", Box((-1, -1, -1), (2, 1, 1)), Box((2.0000001, -1, -1), (5, 1, 1)),
     "every point"),
    ("empty_handle", FIXED, Sphere((10, 10, 10), 0.5), "selects no point"),
])
def test_bad_states_give_the_cli_error_line(bar_path, tmp_path, name, fixed, handle, needle):
    ed = EditorController.open(bar_path)
    ed.add_selector("fixed", fixed)
    ed.add_selector("handle", handle)
    with pytest.raises(RegionError) as info:
        ed.fit()
    message = str(info.value)
    assert needle in message and "\n" not in message
    assert ed.problem() == message and ed.stale
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(ed.to_yaml_dict(output=tmp_path / "out.ply",
                                                   config_dir=tmp_path)))
    run = _cli("deform", str(path))
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and "Traceback" not in run.stderr
    assert not (tmp_path / "out.ply").exists()


def test_save_never_overwrites_the_input(fitted, bar_path, tmp_path):
    before = _digest(bar_path)
    with pytest.raises(InputError, match="refusing to overwrite"):
        fitted.save(model_path=bar_path, config_path=tmp_path / "e.yaml", image=False)
    with pytest.raises(InputError, match="yaml"):
        fitted.save(model_path=tmp_path / "o.ply", config_path=tmp_path / "e.txt", image=False)
    assert _digest(bar_path) == before and not list(tmp_path.iterdir())


def _gaussian_bar(n: int, seed: int) -> sd.PointModel:
    rng = np.random.default_rng(seed)
    bar = bumpy_bar(n, seed=seed)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    g = Gaussians(scale_log=np.log(rng.uniform(0.01, 0.05, (n, 3))).astype(np.float32),
                  rotation=q / np.linalg.norm(q, axis=1, keepdims=True),
                  opacity=rng.normal(size=n).astype(np.float32),
                  sh_dc=rng.normal(size=(n, 3)).astype(np.float32))
    return sd.PointModel(positions=bar.positions, gaussians=g, kind="gaussians")


def test_gaussian_covariances_follow_deform(tmp_path):
    from splatdeform.deform.gaussians import scale_rotation_to_factor

    path = tmp_path / "splats.ply"
    sd.save(_gaussian_bar(1500, seed=8), path)
    ed = EditorController.open(path)
    ed.add_selector("fixed", FIXED)
    ed.add_selector("handle", HANDLE)
    ed.settings.fit.tolerance = 1e-3
    ed.fit()
    frame = ed.set_pose(POSE)
    g = ed.deformed_model().gaussians
    f = scale_rotation_to_factor(g.scale_log, g.rotation)
    ref = f @ f.transpose(0, 2, 1)
    scale = np.abs(ref).max(axis=(1, 2), keepdims=True)
    assert np.abs(frame.covariances - ref).max() / scale.max() < 1e-3
    assert np.all(np.abs(frame.covariances - ref) <= 2e-3 * scale)


# ---- the edit verb in a subprocess -----------------------------------------------------
def _listening(port: int) -> list[str]:
    """Local addresses (hex, /proc/net/tcp*) listening on ``port``."""
    out = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not os.path.exists(table):
            continue
        for row in Path(table).read_text().splitlines()[1:]:
            local, state = row.split()[1], row.split()[3]
            address, hexport = local.split(":")
            if state == "0A" and int(hexport, 16) == port:
                out.append(address)
    return out


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_edit_verb_serves_on_loopback_and_stops_cleanly(bar_path, sig):
    proc, port, url = start_editor(bar_path)
    try:
        opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
        page = opener.open(url, timeout=20).read()
        assert b"<html" in page.lower()
        assert _listening(port) == ["0100007F"]  # 127.0.0.1 only
        proc.send_signal(sig)
        rest, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0, rest
        assert "Traceback" not in rest and "stopped" in rest
    finally:
        if proc.poll() is None:
            proc.kill()


def test_edit_verb_bad_input_is_one_line(tmp_path):
    run = _cli("edit", str(tmp_path / "missing.ply"))
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1
    assert "missing.ply" in run.stderr
    run = _cli("edit", str(tmp_path / "missing.ply"), "--port", "70000")
    assert run.returncode == 2 and "--port" in run.stderr


def test_retired_viser_viewer_is_an_invalid_choice_in_one_line(bar_path):
    run = _cli("edit", str(bar_path), "--viewer", "viser", "--port", "0")
    assert run.returncode == 2 and "Traceback" not in run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "--viewer: invalid choice: 'viser'" in lines[0]
    assert "'page'" in lines[0]


# ---- one real browser ------------------------------------------------------------------
def test_chromium_shows_the_scene(bar_path):
    """The verb's page in headless chromium (software WebGL): the model drawn in the 3D view
    and the panel filled in, once the page says it is ready and has drawn a frame."""
    from io import BytesIO

    from browser import Chromium
    from PIL import Image

    proc, port, url = start_editor(bar_path)
    try:
        with Chromium(size=(1200, 800), timeout=120) as tab:
            tab.open(url)
            tab.wait("window.sdReady === true || !!window.sdError", 120)
            assert tab.eval("window.sdError || ''") == "", tab.console
            tab.wait("window.sdStats.frames > 0", 60)
            image = np.asarray(Image.open(BytesIO(tab.screenshot())).convert("RGB")).astype(int)
            panel_text = tab.eval("document.getElementById('panel').innerText")
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert proc.returncode == 0
    scene = image[:, :860]   # the 3D view, left of the panel (330 px wide)
    drawn = float((np.abs(scene - scene[0, 0]).sum(axis=2) > 60).mean())
    assert drawn > 0.02, f"the model is not drawn ({drawn:.3f})"
    assert "Fit" in panel_text and "Save" in panel_text, panel_text[:500]


def test_default_save_names_keep_a_double_extension(tmp_path):
    """A compressed PLY is saved as x_edited.compressed.ply (its own format), not as a plain
    PLY named x.compressed_edited.ply."""
    import warnings

    from data_tools.synth import gaussian_bar
    from splatdeform.editor.saving import default_paths
    from splatdeform.io import save

    src = tmp_path / "x.compressed.ply"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the lossy write's note
        save(gaussian_bar(400, seed=5), src)
    ed = EditorController.open(src)
    model, config, image = default_paths(ed)
    assert (model.name, config.name, image.name) == ("x_edited.compressed.ply", "x_edit.yaml",
                                                      "x_edit.png")


# ---- control-point pairs (points:, issue 36) ----------------------------------------------
def _points_edit(folder: Path, bar: Path, *, fixed: bool) -> Path:
    """An edit YAML with a pairs file (and optionally a fixed region) next to ``bar``."""
    (folder / "gcp.csv").write_text("x,y,z,X,Y,Z\n3.5,0,0,3.5,0.3,0.1\n4.5,0.2,0,4.6,0.5,0\n"
                                    "2.5,-0.2,0.1,2.5,0,0.2\n4,0,-0.1,4,0.2,0\n")
    text = f"input: {bar.name}\noutput: pts_out.ply\nfit: {{tolerance: 0.001}}\n"
    if fixed:
        text += "regions:\n  fixed: [{box: {min: [-1,-1,-1], max: [1,1,1]}}]\n"
    path = folder / "pts.yaml"
    path.write_text(text + "points:\n  pairs: {file: gcp.csv}\n")
    return path


@pytest.mark.parametrize("fixed", [True, False], ids=["fixed", "pairs-only"])
def test_points_edit_loads_fits_and_saves_points(bar_copy, fixed):
    from splatdeform.editor.session import Session

    folder = bar_copy.parent
    ed = EditorController.open(_points_edit(folder, bar_copy, fixed=fixed))
    assert ed.points is not None and ed.live_handles() == []
    assert ed.problem() is None
    session = Session(ed)
    st = session.state()
    assert st["points"]["n"] == 4 and st["points"]["after"] is None
    st = session.act({"op": "fit"})
    pts = st["points"]
    assert not st["stale"] and st["fit"]["k"] == 3 and len(pts["delta"]) == 3
    # after: the field sends each source onto its target (exact pairs)
    assert np.abs(np.array(pts["after"]) - np.array(pts["targets"])).max() < 1e-5
    sub = folder / "sub"
    sub.mkdir()
    result = ed.save(sub / "m.ply", sub / "e.yaml", image=False)
    data = yaml.safe_load(result.config.read_text())
    assert (sub / data["points"]["pairs"]["file"]).resolve() == (folder / "gcp.csv").resolve()
    assert "handle" not in data and "handles" not in data
    run = _cli("deform", str(result.config), "-o", str(sub / "again.ply"))
    assert run.returncode == 0, run.stderr
    assert (sub / "again.ply").read_bytes() == result.model.read_bytes()
    back = EditorController.from_config(result.config)
    again = Session(back).state()["points"]
    assert again["sources"] == pts["sources"] and again["targets"] == pts["targets"]


def test_chromium_draws_the_pairs(bar_copy):
    """A points: edit in the page: the pairs drawn as line segments source -> target (one per
    pair) with their dots, before any fit."""
    from browser import Chromium

    proc, port, url = start_editor(_points_edit(bar_copy.parent, bar_copy, fixed=True))
    try:
        with Chromium(size=(1000, 700), timeout=120) as tab:
            tab.open(url)
            tab.wait("window.sdReady === true || !!window.sdError", 120)
            assert tab.eval("window.sdError || ''") == "", tab.console
            tab.wait("window.sdDebug.pairs().children.length >= 3", 60)
            segments = tab.eval("window.sdDebug.pairs().children[0].geometry"
                                ".getAttribute('position').count")
            info = tab.eval("document.getElementById('fitfigures').innerText")
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert segments == 8   # 4 pairs, 2 vertices each
    assert "pairs 4" in info
