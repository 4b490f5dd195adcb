"""The editor page's control-point pairs and handle removal in a real headless chromium (issue
48 item 7), driven as a user drives it: "add pair" and a click on the model, a gizmo drag of
the new pair's target, a click on a pair's dot, "remove pair", "remove handle", undo; each
change waited for as a condition on the page's state (no sleeps), then Save and ``deform``."""

from __future__ import annotations

import shutil
import threading
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import yaml
from browser import Chromium
from editor_pairs_edit import deform_again, points_edit

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.editor.page_server import make_server


@pytest.fixture(scope="module")
def bar_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("pairs_page") / "bar.ply"
    sd.save(bumpy_bar(2000, seed=5), path)
    return path


@contextmanager
def _serving(path: Path):
    srv = make_server(path, port=0)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        yield srv
    finally:
        srv.shutdown()
        srv.server_close()


def _open(tab: Chromium, url: str) -> None:
    tab.open(url)
    tab.wait("window.sdReady === true || !!window.sdError", 90)
    assert tab.eval("window.sdError || ''") == "", tab.console


def _click(tab: Chromium, x: float, y: float) -> None:
    tab.mouse("mouseMoved", x, y)
    tab.mouse("mousePressed", x, y, button="left", clickCount=1)
    tab.mouse("mouseReleased", x, y, button="left", clickCount=1)


def _button(tab: Chromium, name: str) -> None:
    tab.eval(f"document.getElementById('{name}').click()")


def _list(v) -> str:
    return str([float(x) for x in v])


def test_page_adds_drags_selects_removes_and_undoes_pairs(bar_path, tmp_path):
    path = points_edit(tmp_path, bar_path)
    with _serving(path) as srv, Chromium(size=(1100, 750)) as tab:
        ed = srv.session.ed
        bar = ed.model.positions
        pick = np.argmin(np.abs(bar[:, 0] - 3.0) + 3 * np.abs(bar[:, 2] - 0.5))
        _open(tab, srv.url())
        _button(tab, "fit")
        tab.wait("sdState().fit && !sdState().stale", 120)
        fit_id = tab.eval("sdState().fit.id")
        # add: "add pair", then a click on the (deformed) model picks the source: where the
        # point drawn under the click was before the deformation
        shown = np.asarray(tab.eval("sdDeformedPositions()")).reshape(-1, 3)
        _button(tab, "pair-add")
        _click(tab, *tab.eval(f"sdScreenOf({_list(shown[pick])})"))
        st = tab.wait("sdState().points.n === 5 && sdState()", 120)
        src = np.asarray(st["points"]["sources"][4]) + ed.origin
        hit = np.argmin(np.abs(bar - src).sum(axis=1))
        assert np.abs(bar[hit] - src).max() < 1e-5   # a model point, where it was ...
        assert np.linalg.norm(shown[hit] - shown[pick]) < 0.05 * ed.model.diagonal()  # drawn there
        assert st["points"]["targets"][4] == st["points"]["sources"][4]
        assert st["fit"]["id"] > fit_id and not st["stale"] and st["can_undo"]
        assert "gcp.csv is not changed" in tab.eval("document.getElementById('status')"
                                                     ".textContent")
        # the new pair is selected: the gizmo drags its target; the drag's end refits
        assert "pair 4 selected" in tab.eval("document.getElementById('pairinfo').textContent")
        x, y = tab.eval("sdGizmoScreen()")
        tab.mouse("mouseMoved", x, y)
        tab.mouse("mousePressed", x, y, button="left", clickCount=1)
        for step in range(1, 6):
            tab.mouse("mouseMoved", x + 2 * step, y - 8 * step, button="left")
        tab.mouse("mouseReleased", x + 10, y - 40, button="left", clickCount=1)
        st = tab.wait(f"sdState().fit.id > {st['fit']['id']} && !sdState().stale && sdState()",
                      120)
        moved = np.asarray(st["points"]["targets"][4])
        assert np.linalg.norm(moved - st["points"]["sources"][4]) > 1e-3 * ed.model.diagonal()
        assert np.abs(np.asarray(st["points"]["after"][4]) - moved).max() < 1e-4  # exact pairs
        # undo: the target back on the source, fitted again
        _button(tab, "undo")
        st = tab.wait("(p => p.targets[4].every((v, j) => v === p.sources[4][j]))"
                      "(sdState().points) && !sdState().stale && sdState()", 120)
        _button(tab, "redo")
        tab.wait("(p => p.targets[4].some((v, j) => v !== p.sources[4][j]))"
                 "(sdState().points) && !sdState().stale", 120)
        # a click on pair 1's target dot selects it; "remove pair" removes it; undo restores it
        _click(tab, *tab.eval("sdScreenOf(sdState().points.targets[1])"))
        tab.wait("document.getElementById('pairinfo').textContent.includes('pair 1 selected')")
        kept = tab.eval("sdState().points.sources[1]")
        _button(tab, "pair-remove")
        st = tab.wait("sdState().points.n === 4 && !sdState().stale && sdState()", 120)
        assert kept not in st["points"]["sources"]
        _button(tab, "undo")
        st = tab.wait("sdState().points.n === 5 && !sdState().stale && sdState()", 120)
        assert st["points"]["sources"][1] == kept
        shown = np.asarray(st["points"]["targets"]) + ed.origin
        tab.eval("sdAct({op: 'save', model: 'out.ply', yaml: 'out.yaml', png: 'out.png'})"
                 ".then(s => { window.sdLastSave = s; })")
        tab.wait("!!window.sdLastSave", 120)
        assert tab.eval("window.sdLastSave.error || ''") == ""
        assert tab.eval("window.sdError || ''") == ""
    saved = yaml.safe_load((tmp_path / "out.yaml").read_text())
    rows = np.asarray(saved["points"]["pairs"])   # inline, the pairs file untouched
    assert rows.shape == (5, 6) and np.allclose(rows[:, 3:], shown)
    assert (tmp_path / "gcp.csv").read_text().count("\n") == 5
    deform_again(tmp_path, "out.yaml", "out.ply")


def test_page_removes_a_handle_and_undo_brings_it_back(bar_path, tmp_path):
    shutil.copy(bar_path, tmp_path / "bar.ply")
    cfg = {"input": "bar.ply", "output": "two.ply", "fit": {"tolerance": 1e-3},
           "regions": {"fixed": [{"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}]},
           "handles": [{"region": [{"box": {"min": [1.8, -1, -1], "max": [2.4, 1, 1]}}],
                        "transform": {"translate": [0, 0.2, 0]}},
                       {"region": [{"box": {"min": [3.5, -1, -1], "max": [5, 1, 1]}}],
                        "transform": {"translate": [0, 0.4, 0]}}]}
    (tmp_path / "two.yaml").write_text(yaml.safe_dump(cfg))
    with _serving(tmp_path / "two.yaml") as srv, Chromium(size=(1100, 750)) as tab:
        _open(tab, srv.url())
        _button(tab, "fit")
        tab.wait("sdState().fit && !sdState().stale", 120)
        # "remove handle" removes the handle the "adds to" choice names
        tab.eval("(() => { const e = document.getElementById('active-handle'); e.value = '0'; "
                 "e.dispatchEvent(new Event('change')); })()")
        _button(tab, "remove-handle")
        st = tab.wait("sdState().handles === 1 && sdState()")
        assert st["stale"] and len(st["poses"]) == 1 and st["poses"][0][1][3] == 0.4
        assert tab.eval("document.getElementById('remove-handle').disabled") is True
        _button(tab, "undo")
        st = tab.wait("sdState().handles === 2 && !sdState().stale && sdState()")
        assert [p[1][3] for p in st["poses"]] == [0.2, 0.4]
        # a handle's row in the tree and "remove selected": that handle goes
        tab.eval("Array.from(document.querySelectorAll('#tree .node'))"
                 ".find(d => d.textContent.startsWith('handle 1')).click()")
        _button(tab, "remove")
        st = tab.wait("sdState().handles === 1 && sdState()")
        assert st["poses"][0][1][3] == 0.2
        _button(tab, "undo")
        tab.wait("sdState().handles === 2 && !sdState().stale")
        assert tab.eval("window.sdError || ''") == ""
    assert len(srv.session.ed.handles) == 2
