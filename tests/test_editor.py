"""The editor: controller (no browser), the viser web layer in-process, the ``edit`` verb in a
subprocess (loopback only, Ctrl-C / SIGTERM end it with exit 0), and one real headless chromium."""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import shared_file

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
    return subprocess.run([sys.executable, "-m", "splatdeform.cli", *args], capture_output=True,
                          text=True, cwd=cwd, timeout=120)


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


# ---- web layer in-process ------------------------------------------------------------------
@pytest.fixture()
def viser_server():
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield server
    server.stop()


def test_app_colours_regions_fits_and_follows_the_pose(bar_copy, viser_server):
    from splatdeform.editor.server import EditorApp, pose_matrix

    ed = EditorController.open(bar_copy)
    ed.settings.fit.tolerance = 1e-3
    app = EditorApp(ed, viser_server)
    try:
        app.start()
        assert "free **2,000**" in app.counts_md.content
        app._add("fixed", "box")
        app._add("handle", "sphere")
        ed.set_selector("fixed", 0, FIXED)
        ed.set_selector("handle", 0, Sphere((4.0, 0, 0), 0.6))
        app.rebuild_selectors()
        app.refresh_regions()
        counts = ed.counts()
        assert f"fixed **{counts['fixed']:,}**" in app.counts_md.content
        colors = app.shown()[1].astype(float)
        fixed, handle = ed.masks()[0], ed.masks()[1][0]
        assert colors[fixed, 2].mean() > colors[~fixed & ~handle, 2].mean()  # blue tint
        assert colors[handle, 0].mean() > colors[fixed, 0].mean()            # orange tint
        app._fit()
        assert not ed.stale and "centers" in app.fit_md.content and app._pose_gizmos
        start, base = app._pose_base[0]
        matrix = pose_matrix(ed.origin, start, start + (0.0, 0.5, 0.0), (1.0, 0, 0, 0)) @ base
        assert np.allclose(matrix[:3, 3], [0, 0.5, 0])
        app.apply_pose(0, matrix)
        shown = app.shown()[0]
        assert np.array_equal(np.sort(shown, axis=0), np.sort(np.asarray(app.node.points), axis=0))
        moved = shown[handle] + ed.origin - ed.model.positions[handle]
        assert np.allclose(moved, [0, 0.5, 0], atol=1e-4)
        assert np.array_equal(shown[fixed], (ed.model.positions[fixed] - ed.origin)
                              .astype(np.float32))
        app.request_pose(0, np.eye(4))                 # through the coalescing worker
        deadline = time.time() + 10
        while app.frames < 1 and time.time() < deadline:
            time.sleep(0.05)
        assert app.frames >= 1
        app._new_handle()                              # a second handle gets the next selector
        app._add("handle", "box")
        assert len(ed.handles) == 2 and len(ed.handles[1].selectors) == 1 and ed.stale
        assert any(label.startswith("handle 1.0") for label in app.selected.options)
    finally:
        app.close()


def test_app_shows_splats_and_meshes(viser_server, tmp_path):
    from splatdeform.editor import view
    from splatdeform.editor.server import EditorApp

    path = tmp_path / "splats.ply"
    sd.save(_gaussian_bar(400, seed=3), path)
    app = EditorApp(EditorController.open(path), viser_server)
    app.close()
    assert app.kind == "splats" and app.up == "-y"
    assert np.asarray(app.node.buffer).shape == (400, 8)
    mesh = EditorController.open(shared_file("scans/bunny_res2.ply"))
    app = EditorApp(mesh, viser_server)
    app.close()
    assert app.kind == "mesh" and app.up == "+y"
    assert np.asarray(app.mesh.faces).shape == (mesh.model.n_faces, 3)
    # viser's own packing of the same splats is byte-identical to ours
    frame = EditorController.open(path).base_frame()
    rgba = np.full((400, 4), 200, np.uint8)
    ours = view.splat_buffer(frame.positions, frame.cov6, rgba)
    handle = viser_server.scene.add_gaussian_splats("/check", frame.positions, frame.covariances,
                                                    rgba[:, :3], rgba[:, 3:])
    theirs = np.asarray(handle.buffer)
    assert np.array_equal(ours, theirs)


# ---- the edit verb in a subprocess -----------------------------------------------------
def _start_editor(path: Path, *args: str) -> tuple[subprocess.Popen, int, str]:
    """The running ``edit`` verb, its port and the URL it printed (with its token)."""
    proc = subprocess.Popen([sys.executable, "-m", "splatdeform.cli", "edit", str(path),
                             "--port", "0", "--viewer", "viser", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 60
    for line in proc.stdout:
        if "splatdeform editor: http://" in line:
            url = line.split("splatdeform editor: ")[1].split()[0]
            port = int(url.split("http://127.0.0.1:")[1].split("/")[0])
            return proc, port, url
        if time.time() > deadline:
            break
    proc.kill()
    raise AssertionError("the editor printed no URL")


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
    proc, port, url = _start_editor(bar_path)
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


# ---- one real browser ------------------------------------------------------------------
def test_chromium_shows_the_scene(bar_path, tmp_path):
    from PIL import Image

    chromium = shutil.which("chromium")
    assert chromium, "chromium is missing: `make test` installs it (APT_PKGS in the Makefile)"
    proc, port, url = _start_editor(bar_path)
    drawn, text, run = 0.0, 0.0, None
    try:
        # A loaded machine can need longer than the page's virtual time for the websocket to
        # bring the scene and the panel: take another screenshot until both are there.
        for attempt, budget in enumerate((20000, 40000, 80000, 80000, 80000)):
            shot = tmp_path / f"shot{attempt}.png"
            run = subprocess.run(
                [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--enable-unsafe-swiftshader",
                 f"--user-data-dir={tmp_path / 'profile'}", "--window-size=1200,800",
                 f"--virtual-time-budget={budget}", f"--screenshot={shot}",
                 url], capture_output=True, text=True, timeout=180)
            assert shot.is_file(), run.stderr[-2000:]
            image = np.asarray(Image.open(shot).convert("RGB")).astype(int)
            scene = image[200:750, 100:800]   # the 3D view, clear of the panel and toasts
            drawn = float((np.abs(scene - scene[0, 0]).sum(axis=2) > 60).mean())
            panel = image[70:400, 875:1180]   # the GUI panel below its header
            text = float((panel.sum(axis=2) < 300).mean())
            if drawn > 0.02 and text > 0.003:
                break
            time.sleep(2)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert proc.returncode == 0
    assert drawn > 0.02, f"the model is not drawn ({drawn:.3f}); {run.stderr[-1000:]}"
    assert text > 0.003, f"the GUI panel shows no text ({text:.4f})"
