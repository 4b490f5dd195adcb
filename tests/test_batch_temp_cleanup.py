"""Hostile inputs, round three (issue 32, item 1): a run changes no file but its outputs.

``batch`` cleans only the atomic writer's own temporary names (``.STEM.<pid>-<8 random>.tmp.EXT``)
whose writer is dead, through the one cleaner in ``io/atomic.py``; a user's look-alike files in
``output_dir`` survive. A real batch run on generated bars, with a real dead pid.
"""

from __future__ import annotations

import os
from pathlib import Path

from helpers import dead_pid, run_cli, write_batch

from data_tools.make_archive import make_scans
from splatdeform.io.atomic import atomic_write, remove_stale_temps, temp_owner

LOOK_ALIKES = [".keep.abcdef12.tmp.ply", ".notes.tmp", ".report.json.123-abcd.tmp.json",
               ".a_deformed.tmp.ply",
               "a_deformed.12-abcdefgh.tmp.ply",
               ".x.0-abcdefgh.tmp.ply", ".x.12-ABCDEFGH.tmp.ply"]


def test_batch_keeps_look_alike_files_in_output_dir(tmp_path: Path) -> None:
    scans = tmp_path / "scans"
    make_scans(scans, 2, 1500, spheres=False, zip_name=None)
    out = tmp_path / "out"
    out.mkdir()
    dead = dead_pid()
    for name in LOOK_ALIKES:
        (out / name).write_text(f"user file {name}")
    stale = out / f".a_deformed.{dead}-abc123xy.tmp.ply"   # exactly the writer's name, dead pid
    stale.write_text("left by a killed run")
    live = out / f".b_deformed.{os.getpid()}-abc123xy.tmp.ply"   # a live writer's: kept
    live.write_text("being written")
    cfg = write_batch(tmp_path / "b.yaml", scans="scans", output_dir="out")
    r = run_cli("batch", cfg, "--workers", "1", "--quiet", timeout=180)
    assert r.returncode == 0, r.stderr
    for name in LOOK_ALIKES:
        assert (out / name).read_text() == f"user file {name}", name
    assert live.read_text() == "being written"
    assert not stale.exists()


def test_one_cleaner_matches_only_the_writers_own_names(tmp_path: Path) -> None:
    out = tmp_path / "scan.ply"
    assert temp_owner(".scan.123-abcdefgh.tmp.ply", out) == 123
    assert temp_owner(".scan.123-abcdefgh.tmp.ply") == 123
    assert temp_owner(".scan.123-abcdefgh.tmp.las", out) is None   # another output's
    assert temp_owner(".other.123-abcdefgh.tmp.ply", out) is None
    for name in LOOK_ALIKES:
        assert temp_owner(name) is None, name
    # a link named exactly like a dead writer's temporary is never removed (nor followed)
    dead = dead_pid()
    target = tmp_path / "precious.txt"
    target.write_text("keep")
    (tmp_path / f".scan.{dead}-abcdefgh.tmp.ply").symlink_to(target)
    plain = tmp_path / f".scan.{dead}-zzzzzzzz.tmp.ply"
    plain.write_text("stale")
    assert remove_stale_temps(out) == [plain]
    assert target.read_text() == "keep"
    # the writer's own temporary name is one the cleaner recognises
    with atomic_write(out) as stream:
        (tmp,) = [p for p in tmp_path.iterdir() if p.name.startswith(".scan.")
                  and p.name.endswith(".tmp.ply") and not p.is_symlink()]
        assert temp_owner(tmp.name, out) == os.getpid()
        stream.write(b"x")
    assert out.read_bytes() == b"x"
