"""The editor's control-point pair actions and handle removal through the session and the
page's real HTTP server (issue 48 item 7): add / move / remove a pair and remove a handle, each
one undo step; a pair change refits a current fit; Save writes the edited pairs inline (the
pairs file is never written) and ``deform`` reproduces the saved model byte for byte; hostile
requests (bad indices, non-finite or malformed coordinates, more than MAX_PAIRS pairs, pairs
``deform`` refuses, the last handle) get one line and change nothing."""

from __future__ import annotations

import hashlib
import shutil
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from editor_client import Client
from editor_pairs_edit import deform_again, points_edit

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.deform.points import MAX_PAIRS
from splatdeform.editor import EditorController
from splatdeform.editor.page_server import EditorHTTPServer, make_server
from splatdeform.editor.session import Session
from splatdeform.errors import InputError

N = 2000


@pytest.fixture(scope="module")
def bar_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("pairs") / "bar.ply"
    sd.save(bumpy_bar(N, seed=5), path)
    return path


def _local(ed: EditorController, p) -> list[float]:
    return [float(v) for v in np.asarray(p, float) - ed.origin]


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ---- the session ---------------------------------------------------------------------------
def test_pairs_are_added_moved_removed_undone_and_saved_inline(bar_path, tmp_path):
    s = Session(EditorController.open(points_edit(tmp_path, bar_path)))
    ed, csv = s.ed, tmp_path / "gcp.csv"
    before_csv = _digest(csv)
    st = s.act({"op": "fit"})
    fit_id = st["fit"]["id"]
    # add: a pair from (3, 0.1, 0) to (3, 0.35, 0); the current fit is refitted at once
    st = s.act({"op": "add_pair", "source": _local(ed, (3, 0.1, 0)),
                "target": _local(ed, (3, 0.35, 0))})
    assert st["points"]["n"] == 5 and not st["stale"] and st["fit"]["id"] == fit_id + 1
    assert "inline" in st["message"] and "gcp.csv is not changed" in st["message"]
    after = np.asarray(st["points"]["after"]) + ed.origin
    assert np.abs(after[4] - (3, 0.35, 0)).max() < 1e-5   # the field sends it onto the target
    # move pair 0's target, then its source
    st = s.act({"op": "move_pair", "index": 0, "target": _local(ed, (3.5, 0.4, 0.1))})
    assert np.allclose(np.asarray(st["points"]["targets"][0]) + ed.origin, (3.5, 0.4, 0.1))
    st = s.act({"op": "move_pair", "index": 0, "source": _local(ed, (3.6, 0, 0))})
    assert np.allclose(np.asarray(st["points"]["sources"][0]) + ed.origin, (3.6, 0, 0))
    assert not st["stale"]
    # remove pair 1; undo brings it back, fitted again
    st = s.act({"op": "remove_pair", "index": 1})
    assert st["points"]["n"] == 4
    st = s.act({"op": "undo"})
    assert st["points"]["n"] == 5 and not st["stale"]
    assert np.allclose(np.asarray(st["points"]["sources"][1]) + ed.origin, (4.5, 0.2, 0))
    st = s.act({"op": "undo"})   # the source move
    assert np.allclose(np.asarray(st["points"]["sources"][0]) + ed.origin, (3.5, 0, 0))
    st = s.act({"op": "redo"})
    assert np.allclose(np.asarray(st["points"]["sources"][0]) + ed.origin, (3.6, 0, 0))
    assert not st["stale"] and st["can_redo"]
    shown = np.asarray(st["points"]["targets"]) + ed.origin
    # Save: the pairs inline, in the edit's units; deform reproduces the model; gcp.csv as it was
    st = s.act({"op": "save", "model": "out.ply", "yaml": "out.yaml", "png": "out.png"})
    assert "wrote" in st["message"], st
    saved = yaml.safe_load((tmp_path / "out.yaml").read_text())
    rows = np.asarray(saved["points"]["pairs"])
    assert rows.shape == (5, 6) and np.allclose(rows[:, 3:], shown)
    assert rows[0].tolist() == [3.6, 0.0, 0.0, 3.5, 0.4, 0.1]
    assert _digest(csv) == before_csv
    deform_again(tmp_path, "out.yaml", "out.ply")


def test_relative_units_stay_relative(bar_path, tmp_path):
    shutil.copy(bar_path, tmp_path / "bar.ply")
    rows = [[0.2, 0.5, 0.5, 0.2, 0.6, 0.5], [0.8, 0.5, 0.5, 0.8, 0.3, 0.5],
            [0.5, 0.2, 0.5, 0.5, 0.2, 0.6], [0.5, 0.5, 0.2, 0.55, 0.5, 0.2],
            [0.5, 0.5, 0.8, 0.5, 0.5, 0.8]]
    cfg = {"input": "bar.ply", "output": "rel_out.ply", "regions": {"units": "relative"},
           "fit": {"tolerance": 1e-3}, "points": {"pairs": rows}}
    (tmp_path / "rel.yaml").write_text(yaml.safe_dump(cfg))
    s = Session(EditorController.open(tmp_path / "rel.yaml"))
    lo, hi = s.ed.model.bbox()
    target = lo + np.array([0.25, 0.7, 0.5]) * (hi - lo)
    s.act({"op": "fit"})
    st = s.act({"op": "move_pair", "index": 0, "target": _local(s.ed, target)})
    assert st["message"] == "" and not st["stale"]
    s.act({"op": "save", "model": "out.ply", "yaml": "out.yaml", "png": "out.png"})
    saved = yaml.safe_load((tmp_path / "out.yaml").read_text())
    assert saved["regions"]["units"] == "relative"
    assert np.allclose(saved["points"]["pairs"][0], [0.2, 0.5, 0.5, 0.25, 0.7, 0.5])
    assert saved["points"]["pairs"][1:] == rows[1:]
    deform_again(tmp_path, "out.yaml", "out.ply")


def test_pairs_start_on_a_bare_model_and_the_last_one_removes_points(bar_path, tmp_path):
    shutil.copy(bar_path, tmp_path / "bar.ply")
    s = Session(EditorController.open(tmp_path / "bar.ply"))
    assert s.state()["points"] is None
    st = s.act({"op": "add_pair", "source": _local(s.ed, (3, 0, 0))})
    assert st["points"]["n"] == 1 and st["points"]["targets"] == st["points"]["sources"]
    st = s.act({"op": "remove_pair", "index": 0})
    assert st["points"] is None and "last pair" in st["message"]
    st = s.act({"op": "undo"})
    assert st["points"]["n"] == 1


def test_the_last_pair_stays_while_check_pairs_need_it(bar_path, tmp_path):
    path = points_edit(tmp_path, bar_path, "  check_pairs: [[3.0, 0.0, 0.0, 3.0, 0.2, 0.0]]\n")
    s = Session(EditorController.open(path))
    for _ in range(3):
        s.act({"op": "remove_pair", "index": 0})
    with pytest.raises(InputError, match="check_pairs need fitted pairs"):
        s.act({"op": "remove_pair", "index": 0})
    assert s.state()["points"]["n"] == 1


def test_a_pair_change_the_fit_refuses_changes_nothing(bar_path, tmp_path):
    """With a current fit, a pair whose source lies in the fixed region is refused by the
    refit: one line, the pairs and the fit as they were."""
    s = Session(EditorController.open(points_edit(tmp_path, bar_path)))
    s.act({"op": "fit"})
    deformation, before = s.ed.deformation, s.state()
    with pytest.raises(InputError, match="regions.fixed"):
        s.act({"op": "add_pair", "source": _local(s.ed, (0, 0, 0)),
               "target": _local(s.ed, (0, 0.2, 0))})
    st = s.state()
    assert st["points"] == before["points"] and not st["stale"]
    assert s.ed.deformation is deformation and not s.history.undo_stack[1:]


def test_a_handle_is_removed_and_undo_brings_it_and_its_fit_back(bar_path, tmp_path):
    shutil.copy(bar_path, tmp_path / "bar.ply")
    cfg = {"input": "bar.ply", "output": "two.ply", "fit": {"tolerance": 1e-3},
           "regions": {"fixed": [{"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}]},
           "handles": [{"region": [{"box": {"min": [1.8, -1, -1], "max": [2.4, 1, 1]}}],
                        "transform": {"translate": [0, 0.2, 0]}},
                       {"region": [{"box": {"min": [3.5, -1, -1], "max": [5, 1, 1]}}],
                        "transform": {"translate": [0, 0.4, 0]}}]}
    (tmp_path / "two.yaml").write_text(yaml.safe_dump(cfg))
    s = Session(EditorController.open(tmp_path / "two.yaml"))
    s.act({"op": "fit"})
    deformation = s.ed.deformation
    st = s.act({"op": "remove_handle", "handle": 0})
    assert st["handles"] == 1 and st["stale"] and st["can_undo"]
    assert np.allclose(np.asarray(st["poses"][0])[:3, 3], (0, 0.4, 0))
    with pytest.raises(InputError, match="at least one handle"):
        s.act({"op": "remove_handle", "handle": 0})
    st = s.act({"op": "undo"})
    assert st["handles"] == 2 and not st["stale"] and s.ed.deformation is deformation
    assert np.allclose(np.asarray(st["poses"][0])[:3, 3], (0, 0.2, 0))
    st = s.act({"op": "redo"})
    s.act({"op": "fit"})
    st = s.act({"op": "save", "model": "out.ply", "yaml": "out.yaml", "png": "out.png"})
    saved = yaml.safe_load((tmp_path / "out.yaml").read_text())
    assert saved["regions"]["handle"] == [{"box": {"min": [3.5, -1.0, -1.0],
                                                   "max": [5.0, 1.0, 1.0]}}]
    assert np.allclose(np.asarray(saved["handle"]["matrix"])[:3, 3], (0, 0.4, 0))
    deform_again(tmp_path, "out.yaml", "out.ply")


# ---- hostile requests over HTTP ------------------------------------------------------------
@pytest.fixture(scope="module")
def server(bar_path, tmp_path_factory) -> Iterator[EditorHTTPServer]:
    folder = tmp_path_factory.mktemp("hostile_pairs")
    srv = make_server(points_edit(folder, bar_path), port=0)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    Client(srv.server_address[1], srv.token).ok({"op": "fit"})
    yield srv
    srv.shutdown()
    srv.server_close()


def _unchanged(srv: EditorHTTPServer, req: dict | bytes, *words: str) -> str:
    """``req`` is refused (400, one line holding ``words``) and changes nothing."""
    c = Client(srv.server_address[1], srv.token)
    before = srv.session.state()
    status, out = c.act(req)
    assert status == 400, out
    line = out["error"]
    assert "\n" not in line and "Traceback" not in line and len(line) < 400, line
    for w in words:
        assert w in line, line
    after = srv.session.state()
    for key in ("points", "fit", "stale", "handles", "poses", "can_undo", "can_redo"):
        assert after[key] == before[key], key
    return line


@pytest.mark.parametrize("index", [-1, 4, 10**12, "0", True, 1.5, None, [0]])
@pytest.mark.parametrize("op", ["move_pair", "remove_pair"])
def test_bad_pair_indices_are_one_line(server, op, index):
    _unchanged(server, {"op": op, "index": index, "target": [0, 0, 0]}, "index",
               "0..3", "the edit has 4 pairs")


@pytest.mark.parametrize("value", [[1, 2], [[1, 2, 3]], ["a", 1, 2], {"x": 1}, "1,2,3",
                                   [True, 0, 0], 7, [1e15, 1e15, 1e15]])
@pytest.mark.parametrize("key", ["source", "target"])
def test_malformed_coordinates_are_one_line(server, key, value):
    words = ("points.pairs",) if value == [1e15] * 3 else (key, "3 finite")
    req = {"op": "move_pair", "index": 0, key: value}
    _unchanged(server, req, *words)
    _unchanged(server, {"op": "add_pair", "source": [0, 0, 0], key: value}, *words)


@pytest.mark.parametrize("body", [b'{"op": "add_pair", "source": [NaN, 0, 0]}',
                                  b'{"op": "move_pair", "index": 0, "target": [0, Infinity, 0]}',
                                  b'{"op": "move_pair", "index": 0, "target": [0, 1e400, 0]}'])
def test_non_finite_coordinates_are_one_line(server, body):
    _unchanged(server, body, "request")


def test_pairs_deform_refuses_are_refused(server):
    st = server.session.state()
    src = st["points"]["sources"]
    _unchanged(server, {"op": "add_pair", "source": src[1], "target": [0, 0, 0]},
               "points.pairs[4] conflicts with points.pairs[1]")
    _unchanged(server, {"op": "move_pair", "index": 0, "source": src[2]}, "conflicts with")
    _unchanged(server, {"op": "add_pair", "source": _local(server.session.ed, (0, 0, 0))},
               "regions.fixed")
    _unchanged(server, {"op": "move_pair"}, "index")
    _unchanged(server, {"op": "move_pair", "index": 0}, "expected a source or a target")
    _unchanged(server, {"op": "add_pair"}, "source")


@pytest.mark.parametrize("handle", [-1, 1, "0", 0.5, None])
def test_bad_handle_removals_are_one_line(server, handle):
    _unchanged(server, {"op": "remove_handle", "handle": handle}, "handle")


def test_the_last_handle_stays(server):
    _unchanged(server, {"op": "remove_handle", "handle": 0}, "at least one handle")


def test_more_than_max_pairs_is_refused(bar_path, tmp_path):
    shutil.copy(bar_path, tmp_path / "bar.ply")
    rng = np.random.default_rng(4)
    src = np.unique(np.round(rng.uniform([0.1, -0.4, -0.4], [3.9, 0.4, 0.4],
                                         (MAX_PAIRS + 50, 3)), 6), axis=0)[:MAX_PAIRS]
    assert src.shape[0] == MAX_PAIRS
    rows = np.hstack([src, src + [0, 0.01, 0]]).tolist()
    (tmp_path / "many.yaml").write_text(yaml.safe_dump(
        {"input": "bar.ply", "output": "many_out.ply", "points": {"pairs": rows}}))
    srv = make_server(tmp_path / "many.yaml", port=0)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        _unchanged(srv, {"op": "add_pair", "source": [0.5, 0.1, 0]},
                   f"at most {MAX_PAIRS:,} pairs")
        c = Client(srv.server_address[1], srv.token)
        assert c.ok({"op": "remove_pair", "index": 0})["points"]["n"] == MAX_PAIRS - 1
    finally:
        srv.shutdown()
        srv.server_close()
