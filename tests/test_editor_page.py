"""The editor's WebGL2 page: its session (undo / redo, poses in local coordinates), the arrays it
uploads, the page's deform shader math read back from a real headless chromium (software WebGL)
against splatdeform/basis/reference.py, and the whole edit driven through the DevTools protocol
(click to place, numeric size, Fit, drag the handle gizmo, undo / redo, Save) compared with a
CLI run of the saved YAML."""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import yaml
from browser import Chromium
from conftest import shared_file

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.basis import reference
from splatdeform.deform import full_basis
from splatdeform.edit.selectors import Box
from splatdeform.editor import EditorController, payload
from splatdeform.editor.page_server import make_server
from splatdeform.editor.session import Session
from splatdeform.errors import InputError

N = 2000


@pytest.fixture(scope="module")
def bar_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("page") / "bar.ply"
    sd.save(bumpy_bar(N, seed=5), path)
    return path


def _local(ed: EditorController, model_point) -> list[float]:
    return [float(v) for v in np.asarray(model_point, float) - ed.origin]


def _fitted_session(path: Path) -> Session:
    s = Session(EditorController.open(path))
    s.ed.settings.fit.tolerance = 1e-3
    s.act({"op": "add_selector", "role": "fixed", "kind": "box",
           "center": _local(s.ed, (0, 0, 0)), "size": [2, 2, 2]})
    s.act({"op": "add_selector", "role": "handle", "kind": "box",
           "center": _local(s.ed, (4, 0, 0)), "size": [2, 2, 2]})
    s.act({"op": "fit"})
    return s


@contextmanager
def _serving(path: Path):
    """The page's server for MODEL or EDIT.yaml ``path`` on a free port, in a thread."""
    srv = make_server(path, port=0)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        yield srv
    finally:
        srv.shutdown()
        srv.server_close()


def _page_save(tab: Chromium, stem: str = "out") -> None:
    """Save through the page's action (model, YAML, PNG named ``stem``); no error."""
    tab.eval(f"sdAct({{op: 'save', model: '{stem}.ply', yaml: '{stem}.yaml', "
             f"png: '{stem}.png'}}).then(s => {{ window.sdLastSave = s; }})")
    tab.wait("!!window.sdLastSave", 120)
    assert tab.eval("window.sdLastSave.error || ''") == ""


# ---- session and payload (no browser) ------------------------------------------------------
def test_new_selectors_are_sized_relative_to_the_model(bar_path):
    s = Session(EditorController.open(bar_path))
    st = s.act({"op": "add_selector", "role": "fixed", "kind": "sphere",
                "center": _local(s.ed, (0, 0, 0))})
    sel = st["selectors"][0]
    assert sel["size"][0] == pytest.approx(0.04 * s.ed.model.diagonal())
    assert np.allclose(sel["center"], _local(s.ed, (0, 0, 0)))
    assert st["counts"]["fixed"] > 0


def test_undo_restores_regions_and_poses_and_keeps_the_fit(bar_path):
    s = _fitted_session(bar_path)
    fit = s.ed.deformation
    pose = np.eye(4)
    pose[:3, 3] = (0, 0.5, 0)
    s.act({"op": "pose", "handle": 0, "matrix": pose.tolist()})       # a drag step
    s.act({"op": "pose", "handle": 0, "matrix": pose.tolist(), "commit": True})
    assert np.allclose(s.ed.handles[0].matrix[:3, 3], (0, 0.5, 0))   # a translation
    # a wrong grab of the fixed box: the fit goes stale ...
    st = s.act({"op": "move_selector", "role": "fixed", "index": 0,
                "center": _local(s.ed, (2, 0, 0))})
    assert st["stale"]
    # ... and undo brings back the regions, the pose and the same fit
    st = s.act({"op": "undo"})
    assert not st["stale"] and s.ed.deformation is fit
    assert np.allclose(st["poses"][0], pose)
    st = s.act({"op": "undo"})
    assert np.allclose(st["poses"][0], np.eye(4)) and st["can_redo"]
    st = s.act({"op": "redo"})
    assert np.allclose(st["poses"][0], pose)
    with pytest.raises(InputError, match="op"):
        s.act({"op": "explode"})


def test_basis_upload_is_the_deform_glsl_layout(bar_path):
    s = _fitted_session(bar_path)
    ed = s.ed
    basis, control = payload.basis_arrays(ed)
    values, grads = full_basis(ed.deformation)
    k = values.shape[1]
    assert basis.shape == (N, 4 * k) and basis.dtype == np.float32
    assert np.array_equal(basis[:, :k], values)
    assert np.array_equal(basis[:, k:].reshape(N, k, 3), grads)
    # delta C from a local pose equals the controller's from the same model-space pose
    m_local = np.eye(4)
    m_local[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    m_local[:3, 3] = (0.3, 0.1, 0)
    ed.handles[0].matrix = payload.local_to_model(ed, m_local)
    ours = (control @ m_local[:3, :3].T + m_local[:3, 3]) - control
    assert np.allclose(ours, ed.delta_c(), atol=1e-9)
    assert np.allclose(payload.model_to_local(ed, ed.handles[0].matrix), m_local)


def test_up_axis_follows_render_up_and_the_renderer_rule(bar_path, tmp_path):
    ed = EditorController.open(bar_path)
    assert payload.up_axis(ed) == "+y"
    cfg = {"input": str(bar_path), "output": str(tmp_path / "o.ply"),
           "regions": {"fixed": [{"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}],
                       "handle": [{"box": {"min": [3, -1, -1], "max": [5, 1, 1]}}]},
           "handle": {"matrix": np.eye(4).tolist()},
           "render": {"output": str(tmp_path / "o.png"), "up": "+z", "size": [320, 160]}}
    (tmp_path / "e.yaml").write_text(yaml.safe_dump(cfg))
    ed = EditorController.open(tmp_path / "e.yaml")
    assert payload.up_axis(ed) == "+z"
    info = payload.scene_info(ed)
    assert info["up_vector"] == [0, 0, 1] and info["normals"] == "file"


def test_display_normals_are_estimated_only_for_clouds(bar_path, tmp_path):
    bar = bumpy_bar(500, seed=1)
    bare = sd.PointModel(positions=bar.positions)
    sd.save(bare, tmp_path / "bare.ply")
    normals, source = payload.display_normals(EditorController.open(tmp_path / "bare.ply"))
    assert source == "estimated"
    assert np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-5)
    # estimated normals agree with the true ones up to sign on most points
    assert np.median(np.abs(np.sum(normals * bar.normals, axis=1))) > 0.9


# ---- the page in a real headless chromium ---------------------------------------------------
@pytest.fixture()
def page_server(bar_path):
    srv = make_server(bar_path, port=0)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()


def _open(tab: Chromium, url: str) -> None:
    tab.open(url)
    tab.wait("window.sdReady === true || !!window.sdError", 90)
    assert tab.eval("window.sdError || ''") == "", tab.console


def _drawn(tab: Chromium, after: int = 0) -> None:
    """Wait until the page has drawn more than ``after`` frames and every draw it has asked for
    has run (its draws run in animation frames, queued before the one awaited here), so that a
    screenshot shows the current state; a condition, not a fixed sleep."""
    tab.wait(f"sdStats.frames > {after}")
    tab.eval("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(() => r(1))))")


def _polar(j: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(j)
    return u @ vt


@pytest.mark.parametrize("handles", [1, 2])
def test_page_shader_math_matches_the_reference(page_server, handles):
    ed = page_server.session.ed
    ed.settings.fit.tolerance = 1e-3
    ed.add_selector("fixed", Box((-1, -1, -1), (1, 1, 1)))
    ed.add_selector("handle", Box((3, -1, -1), (5, 1, 1)))
    ed.fit()
    rng = np.random.default_rng(3)
    n = 300
    pts = rng.uniform(ed.model.bbox()[0], ed.model.bbox()[1], (n, 3))
    ref = reference.compute_basis(pts, ed.deformation.fit)          # float64 oracle
    values, gradients = ref.values, ref.gradients
    if handles == 2:  # k = 8 (two handles): the general path of deform.glsl
        values = np.concatenate([values, 0.5 * values[:, ::-1]], axis=1)
        gradients = np.concatenate([gradients, 0.5 * gradients[:, ::-1]], axis=1)
    k = values.shape[1]
    basis = np.concatenate([values, gradients.reshape(n, 3 * k)], axis=1)
    delta = rng.normal(scale=0.3 * 4 / k, size=(k, 3))   # deformations of the same size
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    a = rng.normal(size=(n, 3, 3)) * 0.05
    cov = a @ a.transpose(0, 2, 1) + 1e-4 * np.eye(3)
    cov6 = cov.reshape(n, 9)[:, [0, 1, 2, 4, 5, 8]]
    local = pts - ed.origin
    with Chromium() as tab:
        _open(tab, page_server.url())
        arg = {"k": k, "positions": local.ravel().tolist(), "normals": normals.ravel().tolist(),
               "cov6": cov6.ravel().tolist(), "basis": basis.ravel().tolist(),
               "delta": delta.ravel().tolist()}
        got = np.asarray(tab.eval(f"sdParity({__import__('json').dumps(arg)})")).reshape(n, 21)
        page_delta = np.asarray(tab.eval(
            f"sdDelta([{np.eye(4).tolist()}], {np.zeros((4, 3)).tolist()})"))
    assert np.allclose(page_delta, 0)
    # the float64 maths of shaders/deform.glsl from the reference basis
    p = local + values @ delta
    jac = np.eye(3) + np.einsum("ka,nkb->nab", delta, gradients)
    cof = np.linalg.inv(jac).transpose(0, 2, 1) * np.linalg.det(jac)[:, None, None]
    nrm = np.einsum("nab,nb->na", cof, normals)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    sig = jac @ cov @ jac.transpose(0, 2, 1)
    rot = np.stack([_polar(j) for j in jac])
    scale = np.abs(p).max()
    assert np.abs(got[:, 0:3] - p).max() < 1e-5 * scale
    assert np.abs(got[:, 3:6] - nrm).max() < 1e-4
    s6 = sig.reshape(n, 9)[:, [0, 1, 2, 4, 5, 8]]
    assert np.abs(got[:, 6:12] - s6).max() < 1e-4 * np.abs(s6).max()
    r_cols = got[:, 12:21].reshape(n, 3, 3).transpose(0, 2, 1)   # the shader writes columns
    # 12 Newton steps converge for the Jacobians of editing (condition number below ~20)
    ok = np.linalg.cond(jac) < 20
    assert ok.mean() > 0.9
    assert np.abs(r_cols - rot)[ok].max() < 1e-4


def test_page_edit_end_to_end_matches_the_cli(bar_path, tmp_path):
    work = tmp_path / "w"
    work.mkdir()
    src = work / "bar.ply"
    shutil.copy(bar_path, src)
    proc = subprocess.Popen([sys.executable, "-m", "splatdeform.cli", "edit", str(src),
                             "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    url = None
    for line in proc.stdout:
        if "splatdeform editor: http://" in line:
            url = line.split()[2]
            break
    assert url, "the editor printed no URL"
    try:
        with Chromium(size=(1100, 750)) as tab:
            _open(tab, url)
            origin = np.asarray(tab.eval(
                "fetch('/api/scene', {headers: {'X-Editor-Token': new URLSearchParams("
                "location.search).get('t')}}).then(r => r.json()).then(s => s.origin)"))

            def place(role: str, kind: str, model_point) -> dict:
                tab.eval(f"document.querySelector('[data-add=\"{role} {kind}\"]').click()")
                x, y = tab.eval(f"sdScreenOf({_as_list(np.asarray(model_point) - origin)})")
                tab.mouse("mousePressed", x, y, button="left", clickCount=1)
                tab.mouse("mouseReleased", x, y, button="left", clickCount=1)
                return tab.wait(f"sdState().selectors.filter(s => s.role === '{role}').length"
                                " && sdState()")

            # a surface point near each end of the bar, clicked on screen
            bar = sd.load(src)
            ends = [bar.positions[np.argmin(np.abs(bar.positions[:, 0] - x) +
                                            3 * np.abs(bar.positions[:, 2] - 0.5))]
                    for x in (0.0, 4.0)]
            st = place("fixed", "box", ends[0])
            assert st["counts"]["fixed"] > 0
            st = place("handle", "box", ends[1])
            assert st["counts"]["handle"] > 0
            # the new handle box is the selected item: the numeric size field edits it
            tab.eval("(() => { for (const id of ['sx', 'sy', 'sz']) { const e = "
                     "document.getElementById(id); e.value = 2.0; e.dispatchEvent(new "
                     "Event('change')); } })()")
            tab.wait("sdState().selectors.find(s => s.role === 'handle').size[1] === 2")
            fixed_before = tab.eval("sdState().selectors.find(s => s.role === 'fixed').size")
            assert fixed_before[1] != 2.0
            tab.eval("document.getElementById('fit').click()")
            tab.wait("sdState().fit && !sdState().stale", 120)
            # drag the pose gizmo's centre handle on screen
            x, y = tab.eval("sdGizmoScreen()")
            tab.mouse("mouseMoved", x, y)
            tab.mouse("mousePressed", x, y, button="left", clickCount=1)
            for step in range(1, 6):
                tab.mouse("mouseMoved", x + 4 * step, y - 12 * step, button="left")
            tab.mouse("mouseReleased", x + 20, y - 60, button="left", clickCount=1)
            tab.wait("sdState().can_undo && sdState().poses[0][1][3] !== 0")
            moved = tab.eval("sdState().poses[0]")
            assert tab.eval("sdStats.poseBytes") <= 1024
            assert tab.eval("sdStats.poses") >= 1
            tab.eval("document.getElementById('undo').click()")
            tab.wait("sdState().poses[0][1][3] === 0")
            tab.eval("document.getElementById('redo').click()")
            tab.wait("sdState().poses[0][1][3] !== 0")
            assert np.allclose(tab.eval("sdState().poses[0]"), moved)
            # the drawn points moved where the page's own P + B dC says
            shown = np.asarray(tab.eval("sdDeformedPositions()")).reshape(-1, 3)
            tab.eval("document.getElementById('save').click()")
            tab.wait("!!window.sdLastSave", 120)
            assert tab.eval("window.sdLastSave.error || ''") == ""
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
    saved_yaml = work / "bar_edit.yaml"
    data = yaml.safe_load(saved_yaml.read_text())
    assert data["backend"] == "auto"
    assert (work / "bar_edit.png").is_file()
    saved = sd.load(work / "bar_edited.ply")
    assert np.abs(saved.positions - origin - shown).max() < 1e-3 * bar.diagonal()
    data["output"] = "again.ply"
    (work / "again.yaml").write_text(yaml.safe_dump(data))
    run = subprocess.run([sys.executable, "-m", "splatdeform.cli", "deform", "again.yaml"],
                         cwd=work, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert (work / "again.ply").read_bytes() == (work / "bar_edited.ply").read_bytes()


def _as_list(v) -> str:
    return str([float(x) for x in v])


def test_scanned_mesh_without_normals_is_shaded(tmp_path):
    from io import BytesIO

    from PIL import Image

    path = shared_file("scans/bunny_res2.ply")
    srv = make_server(path, port=0)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        assert srv.scene["kind"] == "mesh" and srv.scene["normals"] == "none"
        with Chromium(size=(900, 600)) as tab:
            _open(tab, srv.url())
            _drawn(tab)
            img = np.asarray(Image.open(BytesIO(tab.screenshot())).convert("L")).astype(int)
    finally:
        srv.shutdown()
        srv.server_close()
    view_area = img[:, :560]
    bg = np.bincount(view_area.ravel()).argmax()
    model = view_area[np.abs(view_area - bg) > 12]
    assert model.size > 0.03 * view_area.size, "the mesh is not drawn"
    # shaded, not one flat grey: many grey levels with a wide spread
    assert len(np.unique(model)) > 40 and model.std() > 15


def test_splat_scene_is_drawn_sorted_by_the_page(tmp_path):
    from io import BytesIO

    from PIL import Image

    path = shared_file("splats/tile_3dgs_sh3.ply")
    srv = make_server(path, port=0)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        assert srv.scene["kind"] == "splats" and srv.scene["sh_degree"] == 3
        assert srv.scene["up"] == "-y"   # the renderer's rule for 3DGS files
        with Chromium(size=(900, 600)) as tab:
            _open(tab, srv.url())
            _drawn(tab)
            img = np.asarray(Image.open(BytesIO(tab.screenshot())).convert("RGB")).astype(int)
            # the page's back-to-front order is a permutation of all splats
            order = tab.eval(f"Array.from(sdDebug.order().slice(0, {srv.scene['n']}))")
            # the covariance mode is the edit's, and the page's choice recompiles its shader
            assert tab.eval("document.getElementById('covariance').value") == "limited"
            frames = tab.eval("sdStats.frames")
            tab.eval("(() => { const e = document.getElementById('covariance'); "
                     "e.value = 'rotation'; e.dispatchEvent(new Event('change')); })()")
            tab.wait("sdState().covariance === 'rotation'")
            assert tab.eval("window.sdError || ''") == "" and srv.session.ed.settings.gaussians\
                .covariance == "rotation"
            _drawn(tab, frames)   # the recompiled shader's frame
            again = np.asarray(Image.open(BytesIO(tab.screenshot())).convert("RGB")).astype(int)
            assert not any("rror" in m for m in tab.console), tab.console
    finally:
        srv.shutdown()
        srv.server_close()
    assert sorted(int(i) for i in order) == list(range(srv.scene["n"]))
    view_area = img[:, :560]
    bg = view_area[2, 2]
    drawn = (np.abs(view_area - bg).sum(axis=2) > 40).mean()
    assert drawn > 0.05, f"the splats are not drawn ({drawn:.3f})"
    redrawn = (np.abs(again[:, :560] - bg).sum(axis=2) > 40).mean()   # the rotation shader
    assert redrawn > 0.05, f"the splats are not drawn in rotation mode ({redrawn:.3f})"


def test_png_uses_render_size_of_the_loaded_yaml(bar_path, tmp_path):
    from PIL import Image

    work = tmp_path
    shutil.copy(bar_path, work / "bar.ply")
    cfg = {"input": "bar.ply", "output": "bent.ply",
           "regions": {"fixed": [{"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}],
                       "handle": [{"box": {"min": [3, -1, -1], "max": [5, 1, 1]}}]},
           "handle": {"matrix": np.eye(4).tolist()}, "fit": {"tolerance": 1e-3},
           "render": {"output": "bent.png", "size": [320, 160]}}
    (work / "e.yaml").write_text(yaml.safe_dump(cfg))
    s = Session(EditorController.open(work / "e.yaml"))
    s.act({"op": "fit"})
    st = s.act({"op": "save", "model": "out.ply", "yaml": "out.yaml", "png": "out.png"})
    assert "wrote" in st["message"]
    image = Image.open(work / "out.png")
    assert image.size[0] == 320 and image.size[1] >= 160
    assert yaml.safe_load((work / "out.yaml").read_text())["backend"] == "auto"


def test_api_needs_the_printed_token(page_server):
    import urllib.error
    import urllib.request

    host, port = page_server.server_address[:2]
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    with pytest.raises(urllib.error.HTTPError) as err:
        opener.open(f"http://{host}:{port}/api/state", timeout=10)
    assert err.value.code == 403
    assert b"<html" in opener.open(page_server.url(), timeout=10).read().lower()
    req = urllib.request.Request(f"http://{host}:{port}/api/state",
                                 headers={"X-Editor-Token": page_server.token,
                                          "Origin": "http://evil.example"})
    with pytest.raises(urllib.error.HTTPError) as err:
        opener.open(req, timeout=10)
    assert err.value.code == 403


def test_bad_requests_are_one_line_answers(bar_path):
    s = Session(EditorController.open(bar_path))
    for req in ({"op": "pose", "matrix": np.eye(4).tolist()},             # no fit yet
                {"op": "move_selector", "role": "fixed", "index": 3},    # no such selector
                {"op": "add_selector", "role": "fixed", "kind": "box", "center": [1, 2]}):
        with pytest.raises(InputError) as err:
            s.act(req)
        assert "\n" not in str(err.value)
    from splatdeform.editor.session import error_line

    assert error_line(KeyError("role")).startswith("bad request")


@pytest.mark.parametrize("shape", ["rect", "lasso", "brush"])
def test_screen_selection_becomes_an_indices_selector(page_server, shape):
    path = {"rect": [(250, 250), (325, 350), (400, 450)],
            "lasso": [(250, 250), (450, 260), (420, 460), (260, 420), (250, 250)],
            "brush": [(250, 300), (300, 320), (350, 340), (400, 360)]}[shape]
    with Chromium(size=(1000, 700)) as tab:
        _open(tab, page_server.url())
        tab.eval(f"document.getElementById('select-shape').value = '{shape}'; "
                 "document.querySelector('[data-select=\"fixed\"]').click()")
        tab.mouse("mouseMoved", *path[0])
        tab.mouse("mousePressed", *path[0], button="left", clickCount=1)
        for x, y in path[1:]:
            tab.mouse("mouseMoved", x, y, button="left")
        tab.mouse("mouseReleased", *path[-1], button="left", clickCount=1)
        st = tab.wait("sdState().selectors.length && sdState()")
        sel = st["selectors"][0]
        assert sel["type"] == "indices" and sel["role"] == "fixed"
        picked = sel["yaml"]["indices"]
        assert 0 < len(picked) < N and st["counts"]["fixed"] == len(picked)
        positions = np.asarray(tab.eval("sdDeformedPositions()")).reshape(-1, 3)
        screen = np.asarray(tab.eval(f"{positions.tolist()}.map(p => sdScreenOf(p))"))
    # exactly the points drawn inside the shape (oracles: a box test, the winding number,
    # the distance to the stroke's samples)
    if shape == "rect":
        (x0, y0), (x1, y1) = path[0], path[-1]
        inside = ((screen[:, 0] >= x0) & (screen[:, 0] <= x1) & (screen[:, 1] >= y0) &
                  (screen[:, 1] <= y1))
    elif shape == "lasso":
        inside = _winding(np.asarray(path, float), screen) != 0
    else:
        d = np.linalg.norm(screen[:, None, :] - np.asarray(path, float)[None], axis=2)
        inside = d.min(axis=1) <= 20
    expected = np.flatnonzero(inside)
    # points within a hair of the boundary may fall either way (float32 vs float64)
    assert len(set(picked) ^ set(expected.tolist())) <= 2


def _winding(poly: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(M,) winding numbers of points (M, 2) about the closed polygon (P, 2), by summed angles."""
    a = poly[None, :, :] - pts[:, None, :]
    b = np.roll(poly, -1, axis=0)[None, :, :] - pts[:, None, :]
    ang = np.arctan2(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0], (a * b).sum(-1))
    return np.rint(ang.sum(axis=1) / (2 * np.pi)).astype(int)


# ---- gaussians.covariance in the page's Gaussian vertex stage ---------------------------------
@pytest.mark.parametrize("mode", ["jacobian", "rotation", "limited"])
def test_page_covariance_modes_match_numpy(page_server, mode):
    """The page's vertex stage (deform.glsl's J from a basis texture, then shaders/covariance.glsl
    as the page compiles it) against splatdeform/deform/gaussians.py (float64), for mild,
    strongly stretching and folded Jacobians; SH follow the polar rotation in every mode."""
    from fixtures import random_jacobians, random_splats

    from splatdeform.deform.gaussians import deform_gaussians, polar_rotation
    from splatdeform.render.gaussian_data import covariances, log_scale_shape

    n = 400
    scale_log, quat = random_splats(n)
    jac = random_jacobians(n)
    # a basis (k = 4) whose J is the given one: delta C = (e0, e1, e2, 0), gradient k = row k
    # of J - I, values 0 (the position does not move)
    k = 4
    grads = np.zeros((n, k, 3))
    grads[:, :3, :] = jac - np.eye(3)
    basis = np.concatenate([np.zeros((n, k)), grads.reshape(n, 3 * k)], axis=1)
    delta = np.vstack([np.eye(3), np.zeros((1, 3))])
    sigma = covariances(scale_log, quat)
    cov6 = sigma.reshape(n, 9)[:, [0, 1, 2, 4, 5, 8]]
    arg = {"k": k, "mode": mode, "positions": np.zeros(3 * n).tolist(),
           "normals": np.tile([0.0, 0.0, 1.0], n).tolist(), "cov6": cov6.ravel().tolist(),
           "shape": log_scale_shape(scale_log).astype(np.float64).ravel().tolist(),
           "basis": basis.ravel().tolist(), "delta": delta.ravel().tolist()}
    assert page_server.scene["covariance"] == "limited"   # the edit's default
    with Chromium() as tab:
        _open(tab, page_server.url())
        got = np.asarray(tab.eval(f"sdParity({__import__('json').dumps(arg)})")).reshape(n, 21)
    new = deform_gaussians(scale_log, quat, None, jac, covariance=mode)
    want = covariances(new.scale_log, new.rotation)
    g6 = got[:, 6:12]
    a, b, c, d, e, f = g6.T
    page = np.stack([np.stack([a, b, c], -1), np.stack([b, d, e], -1),
                     np.stack([c, e, f], -1)], axis=1)
    err = np.linalg.norm(page - want, axis=(1, 2)) / np.linalg.norm(want, axis=(1, 2))
    ev = np.linalg.eigvalsh(jac @ sigma @ jac.transpose(0, 2, 1))
    cond = ev[:, 2] / np.maximum(np.abs(ev[:, 0]), 1e-300)
    assert err[cond < 1e4].max() <= 2e-4, f"{mode}: page vs numpy {err[cond < 1e4].max():.3g}"
    assert (err <= 2e-4 + 1e-8 * cond).all(), f"{mode}: page vs numpy {err.max():.3g}"
    folded = np.linalg.det(jac) <= 0
    assert folded.sum() >= 8
    cond_j = np.linalg.cond(jac)   # limited's shortcut (cond J <= 2) and its eigen-solve, both
    assert (cond_j < 1.9).sum() > n // 10 and (cond_j > 2.1).sum() > n // 10
    if mode == "rotation":   # refused: the covariance is kept
        assert np.allclose(page[folded], sigma[folded], rtol=1e-5)
    # the limited mode changed what jacobian would draw (needles exist to be limited)
    if mode == "limited":
        plain = jac @ sigma @ jac.transpose(0, 2, 1)
        changed = np.linalg.norm(page - plain, axis=(1, 2)) > 1e-3 * np.linalg.norm(plain,
                                                                                    axis=(1, 2))
        assert changed.sum() > n // 10
    rot = polar_rotation(jac)
    r_cols = got[:, 12:21].reshape(n, 3, 3).transpose(0, 2, 1)
    ok = (np.linalg.cond(jac) < 20) & ~folded
    assert np.abs(r_cols - rot)[ok].max() < 1e-4


def test_splat_save_keeps_the_covariance_mode_and_deform_reproduces_it(tmp_path):
    """The saved YAML names gaussians.covariance and the editor's model used that mode:
    ``deform`` of the saved YAML writes the same bytes."""
    src = shared_file("splats/tile_3dgs_sh3.ply")
    shutil.copy(src, tmp_path / "tile.ply")
    ed = EditorController.open(tmp_path / "tile.ply")
    ed.settings.fit.tolerance = 1e-3
    lo, hi = ed.model.bbox()
    ext = hi - lo
    ed.add_selector("fixed", Box(tuple(lo - ext), tuple(lo + ext * [0.3, 2, 2])))
    ed.add_selector("handle", Box(tuple(lo + ext * [0.75, -1, -1]), tuple(hi + ext)))
    s = Session(ed)
    s.act({"op": "fit"})
    with pytest.raises(InputError, match="gaussians.covariance"):
        s.act({"op": "covariance", "mode": "needles"})
    st = s.act({"op": "covariance", "mode": "rotation"})
    assert s.act({"op": "undo"})["covariance"] == "limited"    # undoable like any change
    st = s.act({"op": "covariance", "mode": "jacobian"})  # not the default: it must reach the YAML
    assert st["covariance"] == "jacobian" and not st["stale"]
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, 0.8, -0.6], [0, 0.6, 0.8]]
    pose[:3, 3] = 0.1 * ext
    s.act({"op": "pose", "matrix": pose.tolist(), "commit": True})
    s.act({"op": "save", "model": "out.ply", "yaml": "out.yaml", "png": "out.png"})
    data = yaml.safe_load((tmp_path / "out.yaml").read_text())
    assert data["gaussians"] == {"covariance": "jacobian"}
    _deform_again(tmp_path, "out.yaml", "out.ply")
    # and the mode matters here: the default (limited) gives other splats
    data["gaussians"] = {"covariance": "limited"}
    data["output"] = "limited.ply"
    (tmp_path / "limited.yaml").write_text(yaml.safe_dump(data))
    subprocess.run([sys.executable, "-m", "splatdeform.cli", "deform", "limited.yaml"],
                   cwd=tmp_path, capture_output=True, text=True, timeout=300, check=True)
    assert (tmp_path / "limited.ply").read_bytes() != (tmp_path / "out.ply").read_bytes()


# ---- selectors of every kind, nested all / not --------------------------------------------------
def _nested_edit(work: Path) -> dict:
    """An EDIT.yaml beside work/bar.ply whose regions use every selector kind, all / not
    nested (written as nested.yaml; returns its mapping)."""
    bar = sd.load(work / "bar.ply")
    far = [int(i) for i in np.flatnonzero(bar.positions[:, 0] > 3.8)[:5]]
    cfg = {
        "input": "bar.ply", "output": "bent.ply",
        "regions": {"units": "model",
                    "fixed": [{"all": [{"box": {"min": [-1.0, -1.0, -1.0], "max": [1.2, 1.0, 1.0]}},
                                       {"not": {"sphere": {"center": [1.2, 0.0, 0.5],
                                                           "radius": 0.3}}}]},
                              {"property": {"name": "x", "max": 0.2}}],
                    "handle": [{"all": [{"plane": {"point": [3.0, 0.0, 0.0],
                                                   "normal": [1.0, 0.0, 0.0]}},
                                        {"not": {"all": [
                                            {"sphere": {"center": [4.0, 0.0, 0.0], "radius": 0.2}},
                                            {"property": {"name": "x", "in": [9.0, 10.0],
                                                          "min": 3.9}}]}}]},
                               {"indices": far}]},
        "handle": {"matrix": [[1, 0, 0, 0.1], [0, 1, 0, 0.3], [0, 0, 1, 0], [0, 0, 0, 1]]},
        "fit": {"tolerance": 1e-3},
    }
    (work / "nested.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return cfg


def test_nested_selectors_are_a_tree_and_survive_the_saved_yaml(bar_path, tmp_path):
    shutil.copy(bar_path, tmp_path / "bar.ply")
    cfg = _nested_edit(tmp_path)
    with _serving(tmp_path / "nested.yaml") as srv:
        with Chromium(size=(1100, 750)) as tab:
            _open(tab, srv.url())
            rows = tab.eval("Array.from(document.querySelectorAll('#tree .node')).map("
                            "d => [Number(d.dataset.depth), d.textContent])")
            # a selector of any kind typed as YAML joins a region (and is undone again)
            tab.eval("document.getElementById('sel-text').value = "
                     "'{not: {not: {box: {min: [3.5, -1, -1], max: [5, 1, 1]}}}}'; "
                     "document.querySelector('[data-text=\"handle\"]').click()")
            st = tab.wait("sdState().selectors.length === 5 && sdState()")
            assert st["selectors"][-1]["yaml"] == {"not": {"not": {"box": {
                "min": [3.5, -1.0, -1.0], "max": [5.0, 1.0, 1.0]}}}}
            typed = tab.eval("Array.from(document.querySelectorAll('#tree .node')).slice(-3)"
                             ".map(d => Number(d.dataset.depth))")
            tab.eval("document.getElementById('undo').click()")
            tab.wait("sdState().selectors.length === 4")
            tab.eval("sdAct({op: 'fit'})")
            tab.wait("sdState().fit && !sdState().stale", 120)
            _page_save(tab)
    texts = [t.strip() for _, t in rows]
    assert rows[0] == [0, "fixed (union)"]
    assert [d for d, _ in rows[1:5]] == [1, 2, 2, 3]          # all > box, not > sphere
    assert texts[1:3] == ["all (intersection)", 'box {"min":[-1,-1,-1],"max":[1.2,1,1]}']
    assert texts[3] == "not (complement)" and texts[4].startswith("sphere")
    assert [d for d, _ in rows[7:]] == [1, 2, 2, 3, 4, 4, 1]  # handle: all > plane, not > all
    assert texts[-1] == "indices (5 points)" and typed == [1, 2, 3]
    saved = yaml.safe_load((tmp_path / "out.yaml").read_text())
    assert saved["regions"]["fixed"] == cfg["regions"]["fixed"]
    assert saved["regions"]["handle"] == cfg["regions"]["handle"]
    assert saved["regions"]["units"] == "model"
    _deform_again(tmp_path, "out.yaml", "out.ply")


# ---- curve edits ---------------------------------------------------------------------------------
def _curve_edit(work: Path, units: str = "model") -> dict:
    """configs/curve_bar.yaml's curve edit beside work/bar.ply (written as curve.yaml)."""
    cfg = {"input": "bar.ply", "output": "bent.ply",
           "regions": {"units": "model",
                       "fixed": [{"box": {"min": [-1.0, -1.0, -1.0], "max": [0.6, 1.0, 1.0]}},
                                 {"box": {"min": [3.4, -1.0, -1.0], "max": [5.0, 1.0, 1.0]}}]},
           "curve": {"control_points": [[1.2, 0.5, 0.0], [1.7, 0.5, 0.0], [2.3, 0.5, 0.0],
                                        [2.8, 0.5, 0.0]],
                     "moved_to": [[1.2, 0.5, 0.0], [1.7, 0.85, 0.0], [2.3, 0.85, 0.0],
                                  [2.8, 0.5, 0.0]],
                     "degree": 3, "parametrization": "chord", "capture_radius": 0.12},
           "fit": {"tolerance": 2e-3}}
    (work / "curve.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return cfg


def _deform_again(work: Path, saved_yaml: str, saved_model: str) -> None:
    data = yaml.safe_load((work / saved_yaml).read_text())
    data["output"] = "again.ply"
    (work / "again.yaml").write_text(yaml.safe_dump(data))
    run = subprocess.run([sys.executable, "-m", "splatdeform.cli", "deform", "again.yaml"],
                         cwd=work, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert (work / "again.ply").read_bytes() == (work / saved_model).read_bytes()


def test_curve_edit_loads_drags_fits_and_saves_what_deform_reproduces(bar_path, tmp_path):
    shutil.copy(bar_path, tmp_path / "bar.ply")
    cfg = _curve_edit(tmp_path)
    s = Session(EditorController.open(tmp_path / "curve.yaml"))
    st = s.state()
    curve = st["curve"]
    o = s.ed.origin
    assert np.allclose(np.asarray(curve["control"]) + o, cfg["curve"]["control_points"])
    assert np.allclose(np.asarray(curve["moved"]) + o, cfg["curve"]["moved_to"])
    assert curve["band"] > 0 and curve["problem"] is None and st["problem"] is None
    assert st["counts"]["handle"] == curve["band"]            # the band is the moving region
    assert (s.ed.labels() == 2).sum() == curve["band"]
    # the drawn curve runs through the snapped control points' spline: its ends are on them
    samples = np.asarray(curve["samples"])
    assert np.allclose(np.asarray(curve["weights"]).sum(axis=1), 1)
    assert np.linalg.norm(samples[0] - np.asarray(curve["control"][0])) < 0.05
    # saved unchanged (no fit yet needed for the YAML): the curve keeps the YAML's numbers
    assert s.ed.to_yaml_dict()["curve"] == cfg["curve"]
    assert "handle" not in s.ed.to_yaml_dict() and "handles" not in s.ed.to_yaml_dict()
    st = s.act({"op": "fit"})
    assert not st["stale"] and st["fit"]["k"] == 4 and st["fit"]["control"] == []
    # the page's delta (moved - control) is the controller's
    assert np.allclose(s.ed.delta_c(), np.subtract(cfg["curve"]["moved_to"],
                                                   cfg["curve"]["control_points"]))
    # drag control point 2's moved point (steps not recorded, the end committed), then undo
    target = np.asarray(st["curve"]["moved"][2]) + [0.0, 0.1, 0.2]
    assert s.act({"op": "move_curve_point", "index": 2, "center": (target - 0.05).tolist(),
                  "moved": True}) == {"ok": 1}
    st = s.act({"op": "move_curve_point", "index": 2, "center": target.tolist(),
                "moved": True, "commit": True})
    assert np.allclose(st["curve"]["moved"][2], target) and not st["stale"]
    st = s.act({"op": "undo"})
    assert np.allclose(np.asarray(st["curve"]["moved"][2]) + o, cfg["curve"]["moved_to"][2])
    st = s.act({"op": "redo"})
    assert np.allclose(st["curve"]["moved"][2], target)
    # moving a control point itself (not its moved point) changes the fit: stale
    st = s.act({"op": "move_curve_point", "index": 1,
                "center": (np.asarray(st["curve"]["control"][1]) + [0.05, 0, 0]).tolist()})
    assert st["stale"]
    st = s.act({"op": "undo"})
    assert not st["stale"]
    st = s.act({"op": "save", "model": "out.ply", "yaml": "out.yaml", "png": "out.png"})
    assert "wrote" in st["message"], st
    saved = yaml.safe_load((tmp_path / "out.yaml").read_text())
    assert saved["curve"]["control_points"] == cfg["curve"]["control_points"]
    assert np.allclose(np.asarray(saved["curve"]["moved_to"][2]) - o, target)
    _deform_again(tmp_path, "out.yaml", "out.ply")
    # the saved model moved where the page's P + B dC puts it (float32 basis upload)
    basis = s.basis()
    k = st["fit"]["k"]
    delta = s.ed.delta_c()
    local = (s.ed.model.positions - o).astype(np.float32) + basis[:, :k] @ delta
    out = sd.load(tmp_path / "out.ply").positions - o
    free = ~s.ed.deformation.fixed
    assert np.abs(out[free] - local[free]).max() < 1e-3 * s.ed.model.diagonal()


def test_curve_drawn_on_a_bare_model_with_a_handle(bar_path, tmp_path):
    """Click control points on the model, fit with a handle too (the handles: form), save."""
    shutil.copy(bar_path, tmp_path / "bar.ply")
    s = Session(EditorController.open(tmp_path / "bar.ply"))
    s.ed.settings.fit.tolerance = 2e-3
    with pytest.raises(InputError, match="curve"):
        s.act({"op": "move_curve_point", "index": 0, "center": [0, 0, 0]})
    s.act({"op": "add_selector", "role": "fixed", "kind": "box",
           "center": _local(s.ed, (0, 0, 0)), "size": [1.2, 2, 2]})
    bar = s.ed.model.positions
    for x in (1.2, 1.7, 2.3):
        p = bar[np.argmin(np.abs(bar[:, 0] - x) + np.abs(bar[:, 1] - 0.5) + np.abs(bar[:, 2]))]
        st = s.act({"op": "add_curve_point", "center": _local(s.ed, p)})
    assert "needs at least 4 control points, got 3" in st["problem"]
    p = bar[np.argmin(np.abs(bar[:, 0] - 2.8) + np.abs(bar[:, 1] - 0.5) + np.abs(bar[:, 2]))]
    st = s.act({"op": "add_curve_point", "center": _local(s.ed, p)})
    st = s.act({"op": "curve_settings", "capture_radius": 0.12})
    assert st["curve"]["band"] > 0 and st["problem"] is None, st["problem"]
    assert "handles" not in s.ed.to_yaml_dict()        # the empty handle is not an edit's
    s.act({"op": "add_selector", "role": "handle", "kind": "box",
           "center": _local(s.ed, (4, 0, 0)), "size": [1.0, 2, 2]})
    st = s.act({"op": "fit"})
    assert st["fit"]["k"] == 8 and len(st["fit"]["control"]) == 4
    pose = np.eye(4)
    pose[:3, 3] = (0, 0.3, 0)
    s.act({"op": "pose", "matrix": pose.tolist(), "commit": True})
    s.act({"op": "move_curve_point", "index": 1, "moved": True, "commit": True,
           "center": (np.asarray(st["curve"]["moved"][1]) + [0, 0.3, 0]).tolist()})
    st = s.act({"op": "save", "model": "out.ply", "yaml": "out.yaml", "png": "out.png"})
    assert "wrote" in st["message"], st
    saved = yaml.safe_load((tmp_path / "out.yaml").read_text())
    assert len(saved["handles"]) == 1 and "curve" in saved
    _deform_again(tmp_path, "out.yaml", "out.ply")


def test_page_curve_edit_drag_and_save(bar_path, tmp_path):
    """The page shows a loaded curve edit (points, band), fits, drags a control point's moved
    point with the gizmo, and saves a YAML that deform reproduces byte for byte."""
    shutil.copy(bar_path, tmp_path / "bar.ply")
    cfg = _curve_edit(tmp_path)
    with _serving(tmp_path / "curve.yaml") as srv:
        with Chromium(size=(1100, 750)) as tab:
            _open(tab, srv.url())
            rows = tab.eval("Array.from(document.querySelectorAll('#tree .node'))"
                            ".map(d => d.textContent.trim())")
            assert rows[-5].startswith("curve (degree 3, band") and rows[-1].startswith("point 3")
            assert tab.eval("sdDebug.curve().children.length") == 3   # points, moved, line
            tab.eval("document.getElementById('fit').click()")
            tab.wait("sdState().fit && !sdState().stale", 120)
            tab.eval("sdSelect({type: 'curve', index: 2})")
            before = tab.eval("sdState().curve.moved[2]")
            x, y = tab.eval("sdGizmoScreen()")
            tab.mouse("mouseMoved", x, y)
            tab.mouse("mousePressed", x, y, button="left", clickCount=1)
            for step in range(1, 6):
                tab.mouse("mouseMoved", x + 3 * step, y - 10 * step, button="left")
            tab.mouse("mouseReleased", x + 15, y - 50, button="left", clickCount=1)
            tab.wait(f"sdState().can_undo && sdState().curve.moved[2][1] !== {before[1]}")
            moved = tab.eval("sdState().curve.moved[2]")
            assert tab.eval("sdStats.poses") >= 1
            shown = np.asarray(tab.eval("sdDeformedPositions()")).reshape(-1, 3)
            _page_save(tab)
            assert tab.eval("window.sdError || ''") == ""
    o = srv.session.ed.origin
    saved = yaml.safe_load((tmp_path / "out.yaml").read_text())
    assert saved["curve"]["control_points"] == cfg["curve"]["control_points"]
    assert np.allclose(np.asarray(saved["curve"]["moved_to"][2]) - o, moved)
    assert not np.allclose(saved["curve"]["moved_to"][2], cfg["curve"]["moved_to"][2])
    out = sd.load(tmp_path / "out.ply").positions - o
    assert np.abs(out - shown).max() < 1e-3 * srv.session.ed.model.diagonal()
    _deform_again(tmp_path, "out.yaml", "out.ply")


def test_page_curve_points_are_clicked_on_the_model(page_server):
    ed = page_server.session.ed
    bar = ed.model.positions
    picks = [bar[np.argmin(np.abs(bar[:, 0] - x) + 3 * np.abs(bar[:, 2] - 0.5))]
             for x in (1.2, 1.7, 2.3, 2.8)]
    with Chromium(size=(1100, 750)) as tab:
        _open(tab, page_server.url())
        tab.eval("document.getElementById('curve-add').click()")
        for i, p in enumerate(picks):
            x, y = tab.eval(f"sdScreenOf({_as_list(np.asarray(p) - ed.origin)})")
            tab.mouse("mousePressed", x, y, button="left", clickCount=1)
            tab.mouse("mouseReleased", x, y, button="left", clickCount=1)
            tab.wait(f"sdState().curve && sdState().curve.control.length === {i + 1}")
        tab.eval("document.getElementById('curve-done').click()")
        tab.eval("(() => { const e = document.getElementById('curve-radius'); e.value = 0.15; "
                 "e.dispatchEvent(new Event('change')); })()")
        st = tab.wait("sdState().curve.capture_radius === 0.15 && sdState()")
        rows = tab.eval("Array.from(document.querySelectorAll('#tree .node'))"
                        ".map(d => d.textContent.trim())")
    control = np.asarray(st["curve"]["control"]) + ed.origin
    # each click placed the point drawn under it (the nearest drawn point within 12 px)
    assert np.abs(control - np.asarray(picks)).max() < 0.05 * ed.model.diagonal()
    assert st["curve"]["band"] > 0 and st["curve"]["problem"] is None
    assert rows[-5].startswith("curve (degree 3") and rows[-1] == "point 3"


def test_saves_from_request_threads_render_every_png(bar_path, tmp_path):
    """The page's server answers each request on a new thread; every Save renders its PNG
    (the second one failed: an OpenGL context is current in one thread only)."""
    shutil.copy(bar_path, tmp_path / "bar.ply")
    s = _fitted_session(tmp_path / "bar.ply")
    from splatdeform.render import View, render_comparison  # a render on this thread first

    render_comparison(s.ed.model, s.ed.model, tmp_path / "first.png", View(size=(32, 32)))
    out = []
    for i in range(2):
        t = threading.Thread(target=lambda i=i: out.append(s.act(
            {"op": "save", "model": f"o{i}.ply", "yaml": f"o{i}.yaml", "png": f"o{i}.png"})))
        t.start()
        t.join()
    assert [o["message"].startswith("wrote") for o in out] == [True, True], out
    assert (tmp_path / "o1.png").stat().st_size > 0


# ---- the Fit panel's figures (issue 35) ----------------------------------------------------------
def test_fit_panel_shows_what_deform_prints_and_long_yaml_wraps(bar_path, tmp_path):
    shutil.copy(bar_path, tmp_path / "bar.ply")
    bar = sd.load(tmp_path / "bar.ply")
    many = [int(i) for i in np.flatnonzero(bar.positions[:, 0] > 3.5)[:60]]   # long YAML
    cfg = {"input": "bar.ply", "output": "bent.ply",
           "regions": {"units": "model",
                       "fixed": [{"box": {"min": [-1.0, -1.0, -1.0], "max": [1.2, 1.0, 1.0]}}],
                       "handle": [{"indices": many},
                                  {"box": {"min": [3.8, -1.0, -1.0], "max": [5.0, 1.0, 1.0]}}]},
           "handle": {"transform": {"translate": [0.0, 0.3, 0.0]}},
           "fit": {"tolerance": 1e-3}}
    (tmp_path / "long.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    with _serving(tmp_path / "long.yaml") as srv:
        with Chromium(size=(1100, 750)) as tab:
            _open(tab, srv.url())
            assert tab.eval("document.getElementById('fitfigures').textContent") == ""
            tab.eval("document.getElementById('fit').click()")
            text = tab.wait("document.getElementById('fitfigures').textContent", 120)
            st = tab.eval("sdState()")
            overflow = tab.eval(
                "(() => { const p = document.getElementById('panel');"
                " return Array.from(p.querySelectorAll('#tree .node')).map("
                "d => d.getBoundingClientRect().right - p.getBoundingClientRect().right); })()")
            wide = tab.eval("document.getElementById('panel').scrollWidth - "
                            "document.getElementById('panel').clientWidth")
    stats, counts = st["fit"]["stats"], st["counts"]
    lines = text.split("\n")
    assert lines[0] == f"method {stats['method']} · centers {stats['centers']:,}"
    assert lines[1].startswith(f"constraints {stats['constraints']:,}")
    if stats["kept"] != stats["constraints"]:
        assert f"(kept {stats['kept']:,})" in lines[1]
    assert lines[2].startswith("boundary error ")
    shown = float(lines[2].split()[2])
    assert shown == pytest.approx(stats["residual"], rel=5e-3)
    assert lines[3].startswith(f"regions: fixed {counts['fixed']:,} · handle "
                               f"{counts['handle']:,} · free {counts['free']:,}")
    assert stats["method"] in ("incremental", "exact") and stats["centers"] > 0
    assert max(overflow) <= 1 and wide <= 1   # the long indices row wraps inside the panel
