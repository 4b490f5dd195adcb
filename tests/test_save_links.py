"""Issue #43 item 0: no output is written through a symbolic link that appears after the checks.

The editor's Save (through its real HTTP server) while links to files outside the save folder
are planted at every output name (model, edit YAML, PNG, the PNG's camera file): right after
the name checks, right before each rename (the documented seams
``splatdeform.io.atomic.after_checks_hook`` / ``before_rename_hook``), and from another thread
at several points of the Save (released by a condition, many repetitions). The outside files
never change; Save either writes plain files in the folder (the rename replaced the link) or
refuses with one line. The same for :func:`atomic_write` / :func:`atomic_path` alone, and a
save folder swapped for a link after the checks is not followed.
"""

from __future__ import annotations

import hashlib
import json
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from editor_client import Client

import splatdeform as sd
from data_tools.synth import bumpy_bar
from splatdeform.editor.page_server import EditorHTTPServer, make_server
from splatdeform.errors import InputError
from splatdeform.io import atomic
from splatdeform.io.atomic import atomic_path, atomic_write, check_io_paths, pinned_outputs

N = 600
NAMES = ("s.ply", "s.yaml", "s.png", "s.camera.json")
VICTIMS = {n: f"victim{Path(n).suffix}" for n in NAMES}


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and not p.is_symlink()}


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("links")
    (root / "work").mkdir()
    (root / "outside").mkdir()
    sd.save(bumpy_bar(N, seed=5), root / "work" / "bar.ply")
    for i, victim in enumerate(sorted(set(VICTIMS.values()))):
        (root / "outside" / victim).write_text(f"the user's own file {i}\n")
    return root


@pytest.fixture(scope="module")
def server(tree) -> Iterator[EditorHTTPServer]:
    srv = make_server(tree / "work" / "bar.ply", port=0)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()


@pytest.fixture(scope="module")
def page(server) -> Client:
    c = Client(server.server_address[1], server.token)
    ed = server.session.ed
    lo, hi = ed.model.bbox()
    span = hi - lo
    mid = (lo + hi) / 2 - ed.origin
    for role, x in (("fixed", 0.1), ("handle", 0.9)):
        center = mid.copy()
        center[0] = (lo[0] + x * span[0]) - ed.origin[0]
        c.ok({"op": "add_selector", "role": role, "kind": "box", "center": list(center),
              "size": list(span * [0.25, 1.2, 1.2])})
    ed.settings.fit.tolerance = 1e-3
    c.ok({"op": "fit"})
    c.ok({"op": "pose", "handle": 0,
          "matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.2], [0, 0, 0, 1]]})
    return c


def _plant(work: Path, outside: Path, name: str) -> None:
    """A link at ``name`` in the save folder to the user's file outside it (unless one is
    there: a file Save made, or a link already)."""
    try:
        (work / name).symlink_to(outside / VICTIMS[name])
    except FileExistsError:
        pass


def _clear(work: Path) -> None:
    for n in NAMES:
        (work / n).unlink(missing_ok=True)


def _save(page: Client) -> tuple[int, dict]:
    return page.act({"op": "save", "model": NAMES[0], "yaml": NAMES[1], "png": NAMES[2]})


def _judge(status: int, out: dict, work: Path, outside: Path, before: dict) -> str:
    """Outside unchanged; a 200 left plain files under every name, a refusal is one line."""
    assert _digest(outside) == before
    if status == 200:
        assert "wrote" in out["message"], out
        for n in NAMES:
            assert (work / n).is_file() and not (work / n).is_symlink(), n
        return "replaced"
    assert status == 400, out
    line = out["error"]
    assert "\n" not in line and "Traceback" not in line and "internal" not in line, line
    return "refused"


def test_links_planted_right_after_the_checks(page, tree, monkeypatch):
    """Every check of the Save plants links at all four names the moment it has passed."""
    work, outside = tree / "work", tree / "outside"
    before = _digest(outside)
    _clear(work)
    monkeypatch.setattr(atomic, "after_checks_hook",
                        lambda outs: [_plant(work, outside, n) for n in NAMES])
    status, out = _save(page)
    monkeypatch.setattr(atomic, "after_checks_hook", None)
    # the first check plants them all: the next check finds a link and refuses it
    assert _judge(status, out, work, outside, before) == "refused"
    assert "symbolic link" in out["error"]
    _clear(work)


def test_links_planted_right_before_each_rename_are_replaced(page, tree, monkeypatch):
    work, outside = tree / "work", tree / "outside"
    before = _digest(outside)
    _clear(work)
    seen: list[str] = []

    def plant(out: Path) -> None:
        seen.append(out.name)
        _plant(work, outside, out.name)
        assert (work / out.name).is_symlink()

    monkeypatch.setattr(atomic, "before_rename_hook", plant)
    status, out = _save(page)
    monkeypatch.setattr(atomic, "before_rename_hook", None)
    assert sorted(seen) == sorted(NAMES)
    assert _judge(status, out, work, outside, before) == "replaced"
    assert json.loads((work / "s.camera.json").read_text())["width"] > 0
    assert sd.load(work / "s.ply").n_points == N
    _clear(work)


@pytest.mark.parametrize("stage", range(6))
def test_links_planted_by_another_thread_during_save(page, tree, monkeypatch, stage):
    """A thread plants links at the four names once the Save reached a point (its k-th check,
    or its k-th rename, released by a condition), over and over, while the Save runs."""
    work, outside = tree / "work", tree / "outside"
    before = _digest(outside)
    reached, stop = threading.Event(), threading.Event()
    counts = {"check": 0, "rename": 0}
    kind, k = ("check", stage) if stage < 3 else ("rename", stage - 3)

    def count(which: str) -> None:
        counts[which] += 1
        if which == kind and counts[which] > k:
            reached.set()

    def planter() -> None:
        reached.wait(120)
        while not stop.is_set():
            for n in NAMES:
                _plant(work, outside, n)

    outcomes = []
    monkeypatch.setattr(atomic, "after_checks_hook", lambda outs: count("check"))
    monkeypatch.setattr(atomic, "before_rename_hook", lambda out: count("rename"))
    for _ in range(3):
        _clear(work)
        reached.clear()
        stop.clear()
        counts.update(check=0, rename=0)
        thread = threading.Thread(target=planter, daemon=True)
        thread.start()
        try:
            status, out = _save(page)
        finally:
            stop.set()
            reached.set()
            thread.join(60)
        outcomes.append(_judge(status, out, work, outside, before))
        for n in NAMES:   # whatever is there now: a plain file Save made, or a planted link
            p = work / n
            assert p.is_symlink() or p.is_file()
    _clear(work)
    assert _digest(outside) == before


def test_a_link_named_to_the_controller_is_refused(page, server, tree):
    """The editor never writes through a link, even one named directly to its API."""
    work, outside = tree / "work", tree / "outside"
    before = _digest(outside)
    link = work / "named.yaml"
    link.symlink_to(outside / "victim.yaml")
    try:
        with pytest.raises(InputError, match="symbolic link"):
            server.session.ed.save(work / "named.ply", link, image=False)
    finally:
        link.unlink()
        (work / "named.ply").unlink(missing_ok=True)
    assert _digest(outside) == before


# ---- the writers alone ----------------------------------------------------------------------
def test_atomic_write_replaces_a_link_planted_before_the_rename(tmp_path, monkeypatch):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "out" / "a.json"
    check_io_paths([], [("output", out)])
    monkeypatch.setattr(atomic, "before_rename_hook", lambda o: o.symlink_to(victim))
    with atomic_write(out) as f:
        f.write(b"new")
    assert victim.read_text() == "precious"
    assert not out.is_symlink() and out.read_bytes() == b"new"


def test_a_link_named_at_check_time_is_written_through(tmp_path):
    """The documented behaviour for a link the user named: written where it pointed when the
    checks ran (the link stays); one planted later is replaced instead."""
    target = tmp_path / "target.txt"
    target.write_text("old")
    named = tmp_path / "named.txt"
    named.symlink_to(target)
    check_io_paths([], [("output", named)])
    with atomic_write(named) as f:
        f.write(b"new")
    assert named.is_symlink() and target.read_text() == "new"
    planted = tmp_path / "planted.txt"
    check_io_paths([], [("output", planted)])
    planted.symlink_to(target)
    with atomic_write(planted) as f:
        f.write(b"mine")
    assert not planted.is_symlink() and planted.read_bytes() == b"mine"
    assert target.read_text() == "new"


def test_a_temporary_file_swapped_for_a_link_is_refused(tmp_path):
    """A writer that opens the temporary path by name: a link put in its place is refused
    before the rename (the output is not replaced by a link)."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "m.txt"
    out.write_text("old")
    with pytest.raises(InputError, match="temporary file was replaced"), atomic_path(out) as tmp:
        tmp.unlink()
        tmp.symlink_to(victim)
    assert out.read_text() == "old" and not out.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.txt", "victim.txt"]


def test_a_save_folder_swapped_for_a_link_is_not_followed(tmp_path):
    work, outside = tmp_path / "work", tmp_path / "outside"
    work.mkdir()
    outside.mkdir()
    out = work / "a.json"
    with pinned_outputs():
        check_io_paths([], [("output", out)])
        work.rename(tmp_path / "moved")
        work.symlink_to(outside, target_is_directory=True)
        with atomic_write(out) as f:
            f.write(b"{}")
        with atomic_path(work / "b.json") as tmp:   # a writer given a path
            tmp.write_bytes(b"[]")
    assert list(outside.iterdir()) == []
    assert (tmp_path / "moved" / "a.json").read_bytes() == b"{}"
    assert (tmp_path / "moved" / "b.json").read_bytes() == b"[]"


def test_inside_pinned_outputs_a_link_output_is_refused(tmp_path):
    (tmp_path / "t").write_text("x")
    (tmp_path / "l.json").symlink_to(tmp_path / "t")
    with pinned_outputs(), pytest.raises(InputError, match="l.json: is a symbolic link"):
        check_io_paths([], [("output", tmp_path / "l.json")])


def test_errors_name_the_output_not_the_temporary_file(tmp_path):
    """A name that fits but whose temporary name does not (or any failure creating the
    temporary file) is reported under the output's path."""
    out = tmp_path / ("r" * 240 + ".json")
    with pytest.raises(OSError) as info, atomic_write(out) as f:
        f.write(b"{}")
    assert info.value.filename == str(out)
    assert list(tmp_path.iterdir()) == []


def test_a_failed_write_leaves_no_folder_it_made(tmp_path):
    out = tmp_path / "a" / "b" / "c.bin"
    with pytest.raises(RuntimeError), atomic_write(out):
        raise RuntimeError("the writer refused")
    assert list(tmp_path.iterdir()) == []
