"""The shared utilities of issue 33 item 5: the one error-line formatter (errors.error_line /
errors.one_line, no doubled ``splatdeform: error: splatdeform:`` prefix on argparse errors), the
one Dask client factory (splatdeform.dask_client) and progress through tqdm only
(splatdeform.progress.LineBar)."""

from __future__ import annotations

import sys
import threading

import pytest

from splatdeform import dask_client as dc
from splatdeform.cli import main
from splatdeform.errors import InputError, error_line, one_line
from splatdeform.progress import LineBar

# ------------------------------------------------------------------------- error_line / one_line


def test_error_line_is_one_line_with_the_type_name_when_empty():
    assert error_line(ValueError("a\n  b\tc ")) == "a b c"
    assert error_line(KeyError()) == "KeyError"
    assert error_line(InputError("bad", key="fit.tolerance", file="e.yaml")) == \
        "e.yaml: fit.tolerance: bad"


@pytest.mark.parametrize("n", [299, 300, 301, 1000])
def test_error_line_limit_cuts_like_the_old_formatters(n):
    text = "x" * (n - 1) + "y"
    old = text if len(text) < 300 else text[:297] + "..."   # batch's archive problems
    assert error_line(RuntimeError(text), limit=300) == old
    assert error_line(RuntimeError(text), limit=300, mark="") == text[:300]   # the CLI's
    assert len(error_line(RuntimeError(text), limit=300)) <= 300


def test_one_line_escapes_control_characters():
    assert one_line("plain: text") == "plain: text"
    assert one_line("a\nb\x1b[31m") == "a\\nb\\x1b[31m"


# ------------------------------------------------------------------- argparse errors, one prefix

VERB_USAGE = [
    ([], "the following arguments are required: command"),
    (["nope"], "argument command: invalid choice: 'nope'"),
    (["deform", "x.yaml", "--bogus"], "unrecognized arguments: --bogus"),
    (["info"], "info: the following arguments are required: model"),
    (["deform"], "deform: the following arguments are required: config"),
    (["deform", "x.yaml", "--workers", "abc"], "deform: argument --workers: invalid int value"),
    (["render"], "render: the following arguments are required"),
    (["select"], "select: the following arguments are required: config"),
    (["edit"], "edit: the following arguments are required"),
    (["batch"], "batch: the following arguments are required: config"),
    (["batch", "b.yaml", "--workers", "x"], "batch: argument --workers: invalid int value"),
]


@pytest.mark.parametrize("argv, expected", VERB_USAGE,
                         ids=[" ".join(argv) or "none" for argv, _ in VERB_USAGE])
def test_usage_errors_have_one_prefix(argv, expected, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"splatdeform: error: {expected}"), err[0]
    assert err[0].count("splatdeform") == 1, err[0]


# ------------------------------------------------------------------------ the Dask client factory


def test_one_connect_timeout_documented():
    assert dc.CONNECT_TIMEOUT_S == 20
    assert "20 s" in dc.__doc__


def test_missing_dask_is_one_input_error_naming_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(InputError) as info:
        dc.require_dask("--workers")
    assert str(info.value) == ("--workers: needs Dask, which is not installed; "
                               "pip install 'splatdeform[dask]'")
    assert info.value.exit_code == 2
    with pytest.raises(InputError, match=r"^--scheduler: needs Dask"):
        with dc.dask_client("tcp://127.0.0.1:1"):
            pass


def test_unreachable_scheduler_is_one_input_error(monkeypatch):
    import distributed  # noqa: F401 - the dask extra: `make test` installs it, fails without

    raised: list[BaseException] = []

    def connect() -> None:
        try:
            with dc.dask_client("tcp://127.0.0.1:1"):
                pass
        except BaseException as exc:  # noqa: BLE001 - handed to the test thread
            raised.append(exc)

    monkeypatch.setattr(dc, "CONNECT_TIMEOUT_S", 1)
    attempt = threading.Thread(target=connect, daemon=True)
    attempt.start()
    attempt.join(timeout=120)   # a hang guard: a connect that never gives up fails loudly
    assert not attempt.is_alive(), "the connect to an unreachable scheduler never gave up"
    with pytest.raises(InputError, match=r"^--scheduler: cannot reach the Dask scheduler at "
                                         r"tcp://127.0.0.1:1: "):
        raise raised[0] if raised else AssertionError("it connected")
    with pytest.raises(InputError, match="cannot reach the Dask scheduler at nope"):
        with dc.dask_client("nope", what="scheduler"):
            pass


# ---------------------------------------------------------------------- progress through tqdm only


def test_line_bar_writes_plain_lines_through_tqdm():
    lines: list[str] = []
    bar = LineBar(total=3, mininterval=0, sink=lines.append,
                  line=lambda d: None if d["n"] == 2 else f"{d['n']}/{d['total']}")
    for _ in range(3):
        bar.update(1)
    bar.close()
    assert lines == ["1/3", "3/3"]   # None: nothing; no start line, no close line, no "\r"


def test_line_bar_respects_its_interval():
    lines: list[str] = []
    bar = LineBar(total=100, mininterval=3600, sink=lines.append, line=lambda d: str(d["n"]))
    for _ in range(100):
        bar.update(1)
    bar.close()
    assert lines == []


def test_batch_progress_prints_a_line_per_scan_on_a_pipe(capsys):
    from splatdeform.batch import _Progress

    progress = _Progress(2, quiet=False)
    progress({"scan": "a.ply", "status": "ok", "seconds": 1.25})
    progress({"scan": "b.ply", "status": "failed", "error": "b.ply: broken"})
    progress.close()
    out = capsys.readouterr()
    assert out.out == "[1/2] a.ply: ok (1.2 s)\n[2/2] b.ply: failed: broken\n"
    assert out.err == ""
    quiet = _Progress(1, quiet=True)
    quiet({"scan": "a.ply", "status": "ok", "seconds": 1.0})
    quiet.close()
    assert capsys.readouterr().out == ""
