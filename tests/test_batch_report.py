"""``splatdeform batch`` round two (issues 27, 20, 26): a report that is always written and safe
to open, archives listed in linear time and refused when their entries overlap, per-worker memory
that holds (estimate from the header, then a hard cap), and the batch config's remaining holes.
Real archives, real worker processes, real chromium.
"""

from __future__ import annotations

import io
import os
import shutil
import subprocess
import tarfile
import zipfile
from html.parser import HTMLParser
from pathlib import Path

import pytest
from helpers import batch_report as report
from helpers import run_cli, write_batch

from data_tools.make_archive import make_scans
from splatdeform.batch.config import Job
from splatdeform.batch.runner import run_local
from splatdeform.batch.sources import Scan, archive_members

HOSTILE = "javascript:alert(document.domain);x.ply"
ASCII_HEAD = b"ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\n" \
             b"property float z\nend_header\n"


@pytest.fixture(scope="module")
def bars(tmp_path_factory) -> list[Path]:
    """Two small generated bar scans (good input)."""
    paths, _ = make_scans(tmp_path_factory.mktemp("bars"), 2, 1500, spheres=False,
                          zip_name=None)
    return paths


def _tar_add(tf: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    tf.addfile(info, io.BytesIO(data))


def list_bomb(rows: int) -> bytes:
    """A PLY whose face element holds ``rows`` one-value uchar lists: tiny compressed, each row
    an array object once read."""
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
            b"property float y\nproperty float z\nelement face %d\n"
            b"property list uchar uchar vertex_indices\nend_header\n" % rows)
    return head + bytes(36) + b"\x01\x00" * rows


class _Links(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.scripts, self.urls, self.handlers = 0, [], []

    def handle_starttag(self, tag: str, attrs: list) -> None:
        self.scripts += tag == "script"
        for key, value in attrs:
            if key in ("href", "src"):
                self.urls.append(value)
            if key.startswith("on"):
                self.handlers.append(key)


def test_hostile_names_cut_headers_and_bad_archives_all_reported(tmp_path: Path, bars) -> None:
    scans = tmp_path / "scans"
    scans.mkdir()
    good = bars[0].read_bytes()
    with zipfile.ZipFile(scans / "names.zip", "w") as zf:
        zf.writestr(HOSTILE, good)
        zf.writestr("<img src=x onerror=alert(1)>.ply", good)
    with tarfile.open(scans / "cut.tar", "w") as tf:
        _tar_add(tf, "first.ply", good)
        _tar_add(tf, "second.ply", good)
    raw = (scans / "cut.tar").read_bytes()
    first = 512 + (len(good) + 511) // 512 * 512
    (scans / "cut.tar").write_bytes(raw[:first + 300])   # the second header cut off
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", encoding="utf-8", errors="surrogateescape") as tf:
        _tar_add(tf, b"caf\xe9.ply".decode("utf-8", "surrogateescape"), good)
    (scans / "latin.tar").write_bytes(buf.getvalue())
    (scans / "broken.zip").write_bytes(b"PK\x03\x04 not really a zip")
    os.makedirs(os.fsencode(scans) + b"/raw")
    with open(os.fsencode(scans) + b"/raw/n\xe4me.ply", "wb") as f:   # a Latin-1 file name
        f.write(good)
    cfg = write_batch(tmp_path / "b.yaml", scans="scans", output_dir="out",
                      render={"size": [64, 64]})
    r = run_cli("batch", cfg, "--workers", "2", "--quiet", timeout=300)
    assert r.returncode == 1, r.stderr
    assert "Traceback" not in r.stderr
    out = tmp_path / "out"
    rows = report(out)
    assert rows[f"names.zip:{HOSTILE}"]["status"] == "ok"
    assert rows["cut.tar:first.ply"]["status"] == "ok"
    cut = [row for name, row in rows.items() if name.endswith("cut.tar")]
    assert len(cut) == 1 and "cut off or unreadable" in cut[0]["error"]
    assert rows["latin.tar:caf\ufffd.ply"]["status"] == "ok"   # replacement character
    bad = [row for name, row in rows.items() if name.endswith("broken.zip")]
    assert len(bad) == 1 and "cannot read the archive" in bad[0]["error"]
    named = [row for name, row in rows.items() if name.endswith("n\ufffdme.ply")]
    assert len(named) == 1 and named[0]["status"] == "ok"
    assert len((out / "report.csv").read_text().splitlines()) == 1 + len(rows) == 8
    page = (out / "index.html").read_text()
    links = _Links()
    links.feed(page)
    assert links.scripts == 0 and not links.handlers
    assert links.urls and all(u.startswith("./") or u in ("report.csv", "report.json")
                              for u in links.urls), links.urls
    # what a browser makes of it: no script element, no handler, no scheme link
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    assert chromium, "chromium is needed (make test installs it)"
    dom = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu",
                          "--dump-dom", (out / "index.html").as_uri()], capture_output=True,
                         text=True, timeout=120).stdout
    seen = _Links()
    seen.feed(dom)
    assert "names.zip" in dom and seen.scripts == 0 and not seen.handlers
    assert all(u.startswith("./") or u in ("report.csv", "report.json") for u in seen.urls)
    assert "javascript:" not in "".join(seen.urls)


def test_overlapping_zip_entries_refused_with_one_row(tmp_path: Path) -> None:
    """300 central-directory entries pointing at one member's data (a zip bomb by overlap)."""
    path = tmp_path / "overlap.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("a.ply", ASCII_HEAD % 1 + b"0 0 0\n" * 1000)
    raw = bytearray(path.read_bytes())
    cd = raw.index(b"PK\x01\x02")
    eocd = raw.index(b"PK\x05\x06")
    entry = bytes(raw[cd:eocd])
    entries = b"".join(entry.replace(b"a.ply", b"%05d"[:0] + f"{i:03d}.p"
                                     .encode()[:5].ljust(5, b"y")) for i in range(300))
    tail = bytearray(raw[eocd:])
    tail[8:10] = tail[10:12] = (300).to_bytes(2, "little")
    tail[12:16] = len(entries).to_bytes(4, "little")
    path.write_bytes(bytes(raw[:cd]) + entries + bytes(tail))
    members = archive_members(path)
    assert len(members) == 1 and "overlap" in (members[0].problem or "")


@pytest.mark.parametrize("kind", ["zip", "tar.gz"])
def test_ten_thousand_broken_members_listed_in_one_pass(tmp_path: Path, kind: str) -> None:
    """Every member is checked from its header while the archive is listed; none reaches a
    worker. The subprocess timeout guards against quadratic listing (it used to take > 600 s;
    the time itself is in benchmarks/bench_batch_archive.py)."""
    n = 10_000
    bad = b"ply\nformat binary_little_endian 1.0\nelement vertex 99\nproperty float x\n" \
          b"end_header\n"
    path = tmp_path / f"many.{kind}"
    if kind == "zip":
        with zipfile.ZipFile(path, "w") as zf:
            for i in range(n):
                zf.writestr(f"m{i:05d}.ply", bad)
    else:
        with tarfile.open(path, "w:gz") as tf:
            for i in range(n):
                _tar_add(tf, f"m{i:05d}.ply", bad)
    cfg = write_batch(tmp_path / "b.yaml", scans=path.name, output_dir="out")
    r = run_cli("batch", cfg, "--workers", "1", "--quiet", timeout=120)
    assert r.returncode == 1, r.stderr[-500:]
    rows = report(tmp_path / "out")
    assert len(rows) == n and all(row["status"] == "failed" for row in rows.values())
    assert all("declares more data" in row["error"] or "truncated" in row["error"]
               for row in rows.values()), next(iter(rows.values()))["error"]


def test_list_bomb_and_ascii_member_refused_before_extraction(tmp_path: Path, bars) -> None:
    path = tmp_path / "bombs.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        zf.writestr("list.ply", list_bomb(8_000_000))   # 16 MB body, a ~40 KB member
        zf.writestr("ascii.ply", ASCII_HEAD % 10_000_000 + b"0 0 0\n" * 10_000_000)   # 60 MB
        zf.write(bars[0], "good.ply")
    assert path.stat().st_size < 400_000
    cfg = write_batch(tmp_path / "b.yaml", scans=path.name, output_dir="out",
                      memory_per_worker_mb=600)
    r = run_cli("batch", cfg, "--workers", "1", "--quiet", timeout=300)
    assert r.returncode == 1, r.stderr
    rows = report(tmp_path / "out")
    assert rows["bombs.zip:good.ply"]["status"] == "ok"
    for name in ("list.ply", "ascii.ply"):
        assert "MiB per worker" in rows[f"bombs.zip:{name}"]["error"]
        assert rows[f"bombs.zip:{name}"]["seconds"] == 0.0   # refused before it reached a worker


def grab_memory(job: Job) -> dict:
    """A task that outgrows any estimate: 3 GiB of touched memory."""
    import numpy as np

    block = np.ones(3 * 2**30, dtype=np.uint8)
    return {"scan": job.scan.name, "status": "ok", "error": str(block[-1])}


def test_worker_memory_cap_fails_the_scan_not_the_machine(tmp_path: Path) -> None:
    job = Job(Scan(str(tmp_path / "x.ply")), {}, str(tmp_path), str(tmp_path / "o.ply"), None,
              None, "h", memory_budget=200 * 2**20)
    rows = run_local([job], 1, lambda row: None, fn=grab_memory)
    assert len(rows) == 1 and rows[0]["status"] == "failed"
    assert "out of memory" in rows[0]["error"] and "200 MiB" in rows[0]["error"]


@pytest.mark.parametrize("keys, expected", [
    ({"workers": True}, "workers"),
    ({"scheduler": ""}, "scheduler"),
    ({"output_dir": ""}, "output_dir"),
    ({"output_dir": "/dev/shm/sd_out"}, "output_dir"),
    ({"output_dir": "scans/sub"}, "output_dir"),
    ({"scans": "scans/*.ply", "output_dir": "scans/sub"}, "output_dir"),
    ({"render": {"size": [0, 0]}}, "render.size"),
    ({"render": {"fov": float("nan")}}, "render.fov"),
    ({"render": {"size": [64, 64], "azimuth": float("inf")}}, "render.azimuth"),
    ({"scan_timeout_s": 1e8}, "scan_timeout_s"),
])
def test_batch_config_holes_exit_2_one_line(tmp_path: Path, bars, keys, expected) -> None:
    scans = tmp_path / "scans"
    scans.mkdir()
    shutil.copy(bars[0], scans / "a.ply")
    cfg = write_batch(tmp_path / "b.yaml", **{"scans": "scans", "output_dir": "out", **keys})
    r = run_cli("batch", cfg, "--workers", "1", timeout=120)
    assert r.returncode == 2, (r.returncode, r.stderr)
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and expected in err[0], err


def test_workers_minus_one_and_huge_timeout(tmp_path: Path, bars) -> None:
    scans = tmp_path / "scans"
    scans.mkdir()
    shutil.copy(bars[0], scans / "a.ply")
    cfg = write_batch(tmp_path / "b.yaml", scans="scans", output_dir="out")
    r = run_cli("batch", cfg, "--workers", "-1", timeout=120)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "--workers" in r.stderr
    cfg = write_batch(tmp_path / "c.yaml", scans="scans", output_dir="out2",
                      scan_timeout_s=1e7)
    r = run_cli("batch", cfg, "--workers", "1", "--quiet", timeout=300)
    assert r.returncode == 0, r.stderr


def test_globs_over_symlink_loops_are_bounded(tmp_path: Path, bars) -> None:
    scans = tmp_path / "scans"
    (scans / "deep").mkdir(parents=True)
    shutil.copy(bars[0], scans / "deep" / "a.ply")
    (scans / "deep" / "loop").symlink_to(scans)
    (scans / "self").symlink_to(".")
    cfg = write_batch(tmp_path / "b.yaml", scans="scans/**/*.ply", output_dir="out")
    r = run_cli("batch", cfg, "--workers", "1", "--quiet", timeout=120)
    assert r.returncode == 0, r.stderr
    assert list(report(tmp_path / "out")) == [str(scans / "deep" / "a.ply")]
    cfg = write_batch(tmp_path / "c.yaml", scans="/**/*.ply", output_dir="out3")
    r = run_cli("batch", cfg, "--workers", "1", "--quiet", timeout=120)
    assert r.returncode == 2 and "narrow it" in r.stderr, r.stderr


def test_report_written_when_the_run_is_interrupted(tmp_path: Path, bars, monkeypatch) -> None:
    """Ctrl-C (or a worker that cannot start) while scans run: the report still lists every
    scan, the unfinished ones as not run, and the error goes on."""
    import splatdeform.batch.runner as runner
    from splatdeform.batch import run_batch

    def interrupted(jobs, workers, on_done, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "run_local", interrupted)
    cfg = write_batch(tmp_path / "b.yaml", scans=[str(p) for p in bars], output_dir="out")
    with pytest.raises(KeyboardInterrupt):
        run_batch(cfg, workers=1, quiet=True)
    rows = report(tmp_path / "out")
    assert len(rows) == 2 and all(r["status"] == "failed" and "not run" in r["error"]
                                  for r in rows.values())


# ---- thumbnails that read (issue 35) -------------------------------------------------------------
OLD_CARD_WIDTH = 540   # px: the report's cards before issue 35


def test_thumbnails_twice_as_wide_and_the_splat_tile_fills_its_panels(tmp_path: Path) -> None:
    import numpy as np
    from browser import Chromium
    from conftest import shared_file
    from PIL import Image

    from splatdeform.batch.report import png_size
    from splatdeform.render.compare import LABEL_HEIGHT

    scans = tmp_path / "scans"
    scans.mkdir()
    shutil.copy(shared_file("splats/tile_3dgs_sh3.ply"), scans / "tile.ply")
    cfg = write_batch(tmp_path / "b.yaml", scans="scans", output_dir="out", render={})
    r = run_cli("batch", cfg, "--workers", "1", "--quiet", timeout=300)
    assert r.returncode == 0, r.stderr
    (row,) = report(tmp_path / "out").values()
    assert row["status"] == "ok" and row["png"], row
    assert row["closeup"] is None   # most of the tile moves: the whole view shows it as large
    width, height = png_size(row["png"])
    assert width >= 2 * OLD_CARD_WIDTH and height >= 2 * 256
    image = np.asarray(Image.open(row["png"]).convert("RGB")).astype(int)[LABEL_HEIGHT:]
    panel = image.shape[1] // 2
    for half in (image[:, :panel], image[:, panel:]):
        drawn = np.abs(half - 255).max(axis=2) > 8
        ys, xs = np.nonzero(drawn)
        span_w = (xs.max() - xs.min() + 1) / half.shape[1]
        span_h = (ys.max() - ys.min() + 1) / half.shape[0]
        assert max(span_w, span_h) >= 0.5, (span_w, span_h)
    with Chromium(size=(1800, 1000)) as tab:
        tab.open((tmp_path / "out" / "index.html").resolve().as_uri())
        shown = tab.wait("document.querySelector('.card img') && "
                         "document.querySelector('.card img').complete && "
                         "document.querySelector('.card img').getBoundingClientRect().width", 60)
    assert shown >= 2 * OLD_CARD_WIDTH


TIP_EDIT = {"regions": {"units": "relative",
                        "fixed": [{"box": {"min": [0, 0, 0], "max": [0.7, 1, 1]}}],
                        "handle": [{"box": {"min": [0.9, 0, 0], "max": [1, 1, 1]}}]},
            "handle": {"transform": {"translate": [0, 0.5, 0]}},
            "fit": {"tolerance": 1e-3, "max_centers": 200}, "backend": "numpy"}


def _ndc(camera_file: Path, points):
    """(M, 2) normalised device coordinates of (M, 3) ``points`` through a camera file, and
    their depths in front of the eye."""
    import numpy as np

    from splatdeform.render.camera import load_camera

    camera, (w, h) = load_camera(camera_file)
    homo = np.c_[points, np.ones(len(points))]
    clip = homo @ (camera.projection(w / h) @ camera.view()).T
    return clip[:, :2] / clip[:, 3:4], clip[:, 3]


@pytest.mark.parametrize("budget", [None, 64], ids=["memory", "streamed"])
def test_the_changed_part_gets_its_own_close_up_in_the_report(tmp_path: Path, budget) -> None:
    """A 5-long bar whose last tenth is lifted (the last 30 % moves): the card shows the whole
    model and a close-up framed on the points that moved, which fill at least half its panels;
    every moved point (before and after) projects inside the close-up's camera. In memory and
    streamed (a 64 MB per-worker budget: the thumbnails drawn from the two files)."""
    import numpy as np
    from PIL import Image

    import splatdeform as sd
    from data_tools.synth import bumpy_bar
    from splatdeform.batch.config import load_batch
    from splatdeform.batch.report import png_size
    from splatdeform.render.camera import camera_sidecar
    from splatdeform.render.compare import LABEL_HEIGHT
    from splatdeform.render.framing import moved_mask

    (tmp_path / "scans").mkdir()
    sd.save(bumpy_bar(4000, length=5.0, radius=0.4, seed=3), tmp_path / "scans" / "bar.ply")
    cfg = write_batch(tmp_path / "b.yaml", TIP_EDIT, scans="scans", output_dir="out",
                      render={"size": [400, 300]},
                      **({} if budget is None else {"memory_per_worker_mb": budget}))
    r = run_cli("batch", cfg, "--workers", "1", "--quiet", timeout=300)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "out"
    (row,) = report(out).values()
    assert row["status"] == "ok" and row["closeup"] == str(out / "bar.changed.png"), row
    assert ("save" in row["timings"]) is (budget is None)   # a streamed run has no save stage
    assert png_size(row["closeup"]) == png_size(row["png"]) == (800, 300 + LABEL_HEIGHT)
    before = sd.load(tmp_path / "scans" / "bar.ply").positions
    after = sd.load(row["output"]).positions
    moved = moved_mask(before, after)
    assert 0.2 < moved.mean() < 0.45   # the free region and the handle, not the fixed part
    spans = {}
    for name, png in (("whole", row["png"]), ("closeup", row["closeup"])):
        ndc, depth = _ndc(camera_sidecar(png), np.concatenate([before[moved], after[moved]]))
        assert (depth > 0).all() and (np.abs(ndc) <= 1.0).all(), (name, np.abs(ndc).max())
        spans[name] = float(np.max(ndc.max(axis=0) - ndc.min(axis=0)) / 2.0)
    assert spans["closeup"] >= 0.8 and spans["closeup"] > 1.5 * spans["whole"], spans
    image = np.asarray(Image.open(row["closeup"]).convert("RGB")).astype(int)[LABEL_HEIGHT:]
    halves = np.array_split(image, 2, axis=1)
    for half in halves:   # the drawn pixels of the changed part span half the panel or more
        ys, xs = np.nonzero(np.abs(half - 255).max(axis=2) > 8)
        assert max((np.ptp(xs) + 1) / half.shape[1], (np.ptp(ys) + 1) / half.shape[0]) >= 0.5
    assert np.abs(halves[0] - halves[1]).mean() > 5   # before and after differ visibly
    page = (out / "index.html").read_text()
    assert page.index('src="./bar.png"') < page.index('src="./bar.changed.png"')
    assert 'width="800" height="318"' in page and "changed part" in page
    assert "closeup" in (out / "report.csv").read_text().splitlines()[0].split(",")
    # a rerun skips the scan (the close-up is there); closeup: false asks for none
    r = run_cli("batch", cfg, "--workers", "1", "--quiet", timeout=300)
    assert r.returncode == 0, r.stderr
    assert report(out)[row["scan"]]["status"] == "skipped"
    assert moved_mask(before, before) is None   # nothing moved: no close-up
    off = write_batch(tmp_path / "c.yaml", TIP_EDIT, scans="scans", output_dir="out2",
                      render={"size": [400, 300], "closeup": False})
    (job,) = load_batch(off).jobs
    assert job.png and job.closeup is None
