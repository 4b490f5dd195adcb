"""Progress of the streamed passes: a tqdm bar when stderr is a terminal, plain lines otherwise
(the format the signal and stream tests wait for), and nothing when quiet."""

from __future__ import annotations

import io
import sys

from splatdeform.edit.stream.progress import Progress


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _run(monkeypatch, stream: io.StringIO, *, quiet: bool = False) -> str:
    monkeypatch.setattr(sys, "stderr", stream)
    p = Progress("pass 9 (test)", 1000, quiet=quiet, every=0.0)
    for _ in range(4):
        p.update(100)
    p.finish()
    return stream.getvalue()


def test_plain_lines_when_not_a_terminal(monkeypatch) -> None:
    text = _run(monkeypatch, io.StringIO())
    lines = text.splitlines()
    assert all(ln.startswith("pass 9 (test): ") for ln in lines)
    assert lines[0].startswith("pass 9 (test): 100/1,000 points (10%, ")
    assert lines[0].endswith(" M points/s)")
    assert lines[-1].startswith("pass 9 (test): 400 points in ") and "\r" not in text


def test_tqdm_bar_on_a_terminal(monkeypatch) -> None:
    text = _run(monkeypatch, _Terminal())
    assert "\r" in text and "pass 9 (test):" in text and "points/s" in text
    assert "100/1,000 points" not in text   # the bar replaces the intermediate lines
    assert text.rstrip().splitlines()[-1].lstrip("\r").startswith("pass 9 (test): 400 points in ")


def test_quiet_says_nothing(monkeypatch) -> None:
    assert _run(monkeypatch, _Terminal(), quiet=True) == ""
    assert _run(monkeypatch, io.StringIO(), quiet=True) == ""
