"""Hostile command lines and faults: outputs never replace inputs, one error line (no traceback),
nothing written on failure, signals and stale temporaries, region counts, attribute lengths.

Every case runs the real CLI in a subprocess (``python -m splatdeform.cli``) on a small generated
bar (``data_tools.synth``), with a timeout so a hang fails instead of blocking the suite.
"""

from __future__ import annotations

import contextlib
import os
import re
import resource
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import base_config, catches_sigterm, one_error_line, snapshot, write_config
from helpers import run_cli as run

import splatdeform as sd
from data_tools.synth import bumpy_bar

N_BAR = 1200
TIMEOUT = 120


@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("hostile")
    sd.save(bumpy_bar(N_BAR, seed=11), root / "bar.ply")
    # a scan-like oriented cloud whose normals are 6.28 long (half of them) and unit (the rest)
    bar = bumpy_bar(N_BAR, seed=12)
    bar.normals[: N_BAR // 2] *= 6.28
    sd.save(sd.PointModel(positions=bar.positions, normals=bar.normals,
                          kind="oriented_cloud"), root / "long_normals.ply")
    return root


# ---------------------------------------------------------------- 1. outputs vs inputs

def _hardlink(src: Path, dst: Path) -> Path:
    dst.unlink(missing_ok=True)
    os.link(src, dst)
    return dst


CLASH_CASES = {
    # name: (extra config keys, extra CLI args, needles); {scans}/{work} are filled in
    "render_is_input_model": ({}, ["--render", "{scans}/bar.ply"], ["--render", ".png"]),
    "render_is_config": ({}, ["--render", "{work}/edit.yaml"], ["--render"]),
    "render_hardlink_to_input": ({}, ["--render", "{work}/link.png"], ["--render", "input model"]),
    "render_cfg_hardlink_to_input": ({"render": {"output": "link.png"}}, [],
                                     ["render.output", "input model"]),
    "render_is_model_output": ({}, ["-o", "{work}/o.ply", "--render", "{work}/o.ply"],
                               ["--render"]),
    "reuse_is_model_output": ({}, ["-o", "{work}/o.ply", "--reuse-file", "{work}/o.ply"],
                              ["--reuse-file", "also"]),
    "reuse_is_render": ({}, ["--render", "{work}/i.png", "--reuse-file", "{work}/i.png"],
                        ["i.png", "also"]),
    "reuse_is_config": ({}, ["--reuse-file", "{work}/edit.yaml"], ["--reuse-file", "edit config"]),
    "output_is_config": ({}, ["-o", "{work}/edit.ply"], ["-o/--output", "edit config"]),
    "frames_gif_is_input": ({}, ["--render", "{work}/link.png", "--frames", "3"],
                            ["--render", "link.gif"]),
}


@pytest.mark.parametrize("name", sorted(CLASH_CASES))
def test_output_never_replaces_an_input(name, scans, tmp_path):
    extra, cli, needles = CLASH_CASES[name]
    work = tmp_path / "work"
    cfg = write_config(work, base_config(scans, **extra))
    _hardlink(scans / "bar.ply", work / "link.png")
    _hardlink(scans / "bar.ply", work / "link.gif")
    if name == "output_is_config":  # a config whose name ends in .ply, given as the -o output
        cfg = write_config(work, base_config(scans), "edit.ply")
    before = snapshot(scans, work)
    args = [a.format(scans=scans, work=work) for a in cli]
    res = run("deform", cfg, *args, cwd=work)
    one_error_line(res, 2, needles)
    assert snapshot(scans, work) == before  # inputs untouched, nothing written


def test_render_verb_output_is_input(scans, tmp_path):
    link = _hardlink(scans / "bar.ply", tmp_path / "link.png")
    before = snapshot(scans, tmp_path)
    res = run("render", scans / "bar.ply", "-o", link, cwd=tmp_path)
    one_error_line(res, 2, ["-o/--output", "model"])
    assert snapshot(scans, tmp_path) == before


@pytest.mark.parametrize("kind", ["fifo", "folder", "device"])
def test_non_regular_output_refused(kind, scans, tmp_path):
    target = tmp_path / "o.ply"
    if kind == "fifo":
        os.mkfifo(target)
    elif kind == "folder":
        target.mkdir()
    else:
        target = Path("/dev/null")
    cfg = write_config(tmp_path, base_config(scans))
    before = snapshot(tmp_path)
    res = run("deform", cfg, "-o", target, cwd=tmp_path)
    one_error_line(res, 2, ["-o/--output", "regular file"])
    assert snapshot(tmp_path) == before
    assert kind != "device" or stat.S_ISCHR(os.stat("/dev/null").st_mode)


# ---------------------------------------------------------------- 2. one line, not a traceback

HOSTILE_CONFIGS = {
    # name: (mutation of the config dict, or raw YAML text; needles)
    "index_overflow": (lambda c: c["regions"].update(fixed=[{"indices": [2**63]}]),
                       ["regions.fixed[0].indices[0]"]),
    "deep_yaml": ("a: " + "[" * 100_000 + "]" * 100_000 + "\n", ["edit.yaml", "nested"]),
    "nan_curve_point": ("curve", ["curve.control_points", "finite"]),
    "near_duplicate_curve_points": ("dupes", ["curve.control_points", "same model point"]),
    "too_many_curve_points": ("many", ["curve.control_points"]),
    "render_size_zero": (lambda c: c.update(render={"output": "a.png", "size": [0, 0]}),
                         ["render.size"]),
    "render_size_huge": (lambda c: c.update(render={"output": "a.png",
                                                    "size": [100000, 100000]}),
                         ["render.size"]),
    "render_fov_nan": (lambda c: c.update(render={"output": "a.png", "fov": float("nan")}),
                       ["render.fov", "finite"]),
    "render_output_not_png": (lambda c: c.update(render={"output": "a.ply"}),
                              ["render", ".png"]),
    "render_frames_too_many": (lambda c: c.update(render={"output": "a.gif", "frames": 5000}),
                               ["render.frames"]),
    "translate_nan": (lambda c: c["handle"]["transform"].update(translate=[float("nan"), 0, 0]),
                      ["handle.transform.translate"]),
    "indices_file_fifo": ("fifo", ["idx.txt", "named pipe"]),
}


def _curve_config(scans: Path, points: list[list[float]]) -> dict:
    cfg = base_config(scans)
    del cfg["handle"], cfg["regions"]["handle"]
    cfg["curve"] = {"control_points": points,
                    "moved_to": [[x, y + 0.1, z] for x, y, z in points],
                    "capture_radius": 0.15}
    return cfg


def _hostile_config(name: str, scans: Path, work: Path) -> dict | str:
    case = HOSTILE_CONFIGS[name][0]
    if isinstance(case, str) and case.startswith("a: "):
        return case
    if case == "curve":
        return _curve_config(scans, [[1.5, 0.5, 0], [float("nan"), 0.5, 0], [2.5, 0.5, 0],
                                     [2.8, 0.5, 0]])
    if case == "dupes":  # 40 near-duplicates (repeated knots once snapped) between two points
        return _curve_config(scans, [[1.5, 0.5, 0]] + [[2.0 + 1e-7 * i, 0.5, 0]
                                                         for i in range(40)] + [[2.8, 0.5, 0]])
    if case == "many":  # 2,000 near-duplicate control points
        return _curve_config(scans, [[2.0 + 1e-7 * i, 0.5, 0] for i in range(2000)])
    if case == "fifo":
        os.mkfifo(work / "idx.txt")
        cfg = base_config(scans)
        cfg["regions"]["handle"] = [{"indices": {"file": "idx.txt"}}]
        return cfg
    cfg = base_config(scans)
    case(cfg)
    return cfg


@pytest.mark.parametrize("name", sorted(HOSTILE_CONFIGS))
def test_hostile_config_one_line(name, scans, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    cfg = write_config(work, _hostile_config(name, scans, work))
    before = snapshot(scans, work)
    res = run("deform", cfg, cwd=work)
    one_error_line(res, 2, HOSTILE_CONFIGS[name][1])
    assert snapshot(scans, work) == before  # no model left behind by a bad render setting


@pytest.mark.parametrize("args, needles", [
    (["--frames", "100000"], ["--frames", "1000"]),
    (["--frames", "-1"], ["--frames"]),
    (["-o", "out/" + "a" * 250 + ".ply"], ["name too long"]),
    (["-o", "{work}/edit.yaml/x.ply"], ["not a directory"]),
    (["--reuse-file", "{work}"], ["--reuse-file", "directory"]),
    (["-o", "out/x.foo"], ["out/x.foo", "extension"]),
])
def test_bad_paths_and_flags(args, needles, scans, tmp_path):
    work = tmp_path / "work"
    cfg = write_config(work, base_config(scans))
    before = snapshot(scans, work)
    res = run("deform", cfg, *[a.format(work=work) for a in args], cwd=work)
    one_error_line(res, 2, needles)
    assert snapshot(scans, work) == before


def test_nul_byte_in_config_paths(scans, tmp_path):
    for key, value in (("output", "out/be\0nt.ply"), ("input", str(scans / "b\0ar.ply"))):
        work = tmp_path / key
        cfg = base_config(scans)
        cfg[key] = value
        path = write_config(work, cfg)
        res = run("deform", path, cwd=work)
        one_error_line(res, 2, ["NUL"])
        assert sorted(work.iterdir()) == [path]


def test_invalid_reuse_cache(scans, tmp_path):
    cfg = write_config(tmp_path, base_config(scans))
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip at all\n" * 10)
    res = run("deform", cfg, "--reuse-file", junk, cwd=tmp_path)
    one_error_line(res, 2, ["junk.npz", "precomputed deformation"])
    assert not (tmp_path / "out").exists()
    assert junk.read_bytes() == b"not a zip at all\n" * 10


def _limit_file_size(limit: int):
    def pre() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a kill
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return pre


def test_full_disk_one_line_nothing_left(scans, tmp_path):
    """A write that runs out of space (RLIMIT_FSIZE: the file size limit) fails with one line,
    exit 1, and leaves neither the output nor a temporary file (nor the folder made for it)."""
    cfg = write_config(tmp_path, base_config(scans))
    res = run("deform", cfg, cwd=tmp_path, preexec_fn=_limit_file_size(4096))
    line = one_error_line(res, 1)
    assert "too large" in line.lower() or "space" in line.lower(), line
    assert not (tmp_path / "out").exists()


@contextlib.contextmanager
def _read_only_folder(path: Path):
    """A folder nobody may write to: a read-only tmpfs when running as root (root ignores
    permission bits), else chmod 0555. Skips when neither is possible."""
    path.mkdir()
    if os.geteuid() != 0:
        path.chmod(0o555)
        try:
            yield path
        finally:
            path.chmod(0o755)
        return
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(path)],
                         capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"running as root and cannot mount a read-only tmpfs: {res.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", str(path)], check=False)


def test_read_only_output_folder(scans, tmp_path):
    cfg = write_config(tmp_path, base_config(scans))
    with _read_only_folder(tmp_path / "ro") as ro:
        res = run("deform", cfg, "-o", ro / "x.ply", cwd=tmp_path)
        one_error_line(res, 2, ["ro/x.ply", "not writable"])
        res = run("deform", cfg, "-o", ro / "sub" / "x.ply", cwd=tmp_path)
        one_error_line(res, 2, ["not writable"])
        assert list(ro.iterdir()) == []


def test_huge_translate_writes_nothing(scans, tmp_path):
    cfg = base_config(scans)
    cfg["handle"]["transform"]["translate"] = [1e300, 0, 0]
    path = write_config(tmp_path, cfg)
    res = run("deform", path, cwd=tmp_path)  # refused at load, before any numpy overflow
    one_error_line(res, 2, ["handle.transform.translate", "1e+15"])
    assert not (tmp_path / "out").exists()


def test_info_json_into_closed_pipe(scans, tmp_path):
    proc = subprocess.Popen([sys.executable, "-m", "splatdeform.cli", "info", "--json",
                             str(scans / "bar.ply")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, cwd=tmp_path)
    proc.stdout.close()  # the reader is gone before anything is written (| head -0)
    _, err = proc.communicate(timeout=TIMEOUT)
    assert b"Traceback" not in err and b"Exception ignored" not in err, err
    assert proc.returncode in (0, 141), (proc.returncode, err)


# ---------------------------------------------------------------- 3. finite output

def test_huge_translate_api_raises(scans):
    from splatdeform.errors import InputError

    model = sd.load(scans / "bar.ply")
    x = model.positions[:, 0]
    deformation = sd.prepare_handle(model, x <= 1.0, x >= 3.0, tolerance=1e-3, backend="numpy")
    matrix = np.eye(4)
    matrix[0, 3] = 1e300
    with pytest.raises(InputError, match="non-finite or out-of-range"):
        sd.apply(deformation, model, sd.delta_for(deformation, matrix), moving_matrix=matrix)


# ---------------------------------------------------------------- 4. faults

@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc")
def test_sigterm_cleans_up(tmp_path):
    big = tmp_path / "big.ply"
    sd.save(bumpy_bar(60000, seed=3), big)
    cfg = base_config(tmp_path)
    cfg["input"] = str(big)
    path = write_config(tmp_path, cfg)
    proc = subprocess.Popen([sys.executable, "-m", "splatdeform.cli", "deform", str(path),
                             "--reuse"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            cwd=tmp_path, text=True)
    deadline = time.monotonic() + 60
    while not catches_sigterm(proc.pid) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGTERM)  # the handler is in place; loading/fitting has not ended
    out, err = proc.communicate(timeout=TIMEOUT)
    assert proc.returncode == 143, (proc.returncode, out, err)
    assert "Traceback" not in err and err.strip() == "splatdeform: terminated", err
    leftovers = [p.name for p in tmp_path.rglob("*") if ".tmp" in p.name]
    assert leftovers == [] and not (tmp_path / "out" / "bent.ply").exists()


def test_stale_temps_removed_on_next_run(scans, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    dead = 2**22 + 12345  # above Linux's largest pid: no such process
    stale = [out / f".bent.{dead}-k3j9x2ab.tmp.ply",
             out / f".bent.ply.deform.{dead}-q8w7e6r5.tmp.npz"]
    live = out / f".bent.{os.getpid()}-abcdefgh.tmp.ply"  # a writer that is still running
    other = out / f".other.{dead}-k3j9x2ab.tmp.ply"  # another output's: not ours to judge
    # names that merely look temporary are a user's files: no pid, or not tempfile's random
    users = [out / ".bent.k3j9x2ab.tmp.ply", out / f".bent.{dead}-K3J9X2AB.tmp.ply",
             out / f".bent.{dead}-abc.tmp.ply", out / f".bent.{dead}-k3j9x2abc.tmp.ply"]
    link_target = tmp_path / "precious.ply"
    link_target.write_bytes(b"precious")
    link = out / f".bent.{dead}-linkxxxx.tmp.ply"  # a link is never removed, nor its target
    link.symlink_to(link_target)
    for p in [*stale, live, other, *users]:
        p.write_bytes(b"partial")
    cfg = write_config(tmp_path, base_config(scans))
    res = run("deform", cfg, "--reuse", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert not any(p.exists() for p in stale)
    assert live.exists() and other.exists() and all(p.read_bytes() == b"partial" for p in users)
    assert link.is_symlink() and link_target.read_bytes() == b"precious"
    assert (out / "bent.ply").is_file() and (out / "bent.ply.deform.npz").is_file()


def test_keep_file_beside_the_output_survives(scans, tmp_path):
    """A user's ``.keep.abcdef12.tmp.ply`` beside the output ``keep.ply`` is not a temporary
    file of ours (no pid): it is left alone."""
    keep = tmp_path / ".keep.abcdef12.tmp.ply"
    keep.write_bytes(b"mine")
    res = run("deform", write_config(tmp_path, base_config(scans)), "-o", tmp_path / "keep.ply",
              cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert keep.read_bytes() == b"mine" and (tmp_path / "keep.ply").is_file()


def test_output_links(scans, tmp_path):
    """A dangling link named as the output is refused (the link stays); a link to a file is
    written through (the link stays a link, its target gets the model)."""
    work = tmp_path / "in"
    work.mkdir()
    dangling = work / "out.ply"
    dangling.symlink_to(tmp_path / "nowhere" / "x.ply")
    cfg = write_config(work, base_config(scans))
    res = run("deform", cfg, "-o", dangling, cwd=tmp_path)
    one_error_line(res, 2, ["out.ply", "symbolic link"])
    assert dangling.is_symlink() and not (tmp_path / "nowhere").exists()
    target = tmp_path / "target.ply"
    target.write_bytes(b"old")
    link = work / "via.ply"
    link.symlink_to(target)
    res = run("deform", cfg, "-o", link, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert link.is_symlink() and sd.load(target).n_points == N_BAR


# ---------------------------------------------------------------- 5. select

def test_select_counts_match_deform(scans, tmp_path):
    cfg = base_config(scans, render={"output": "img.png", "size": [320, 160]})
    path = write_config(tmp_path, cfg)
    res = run("select", path, "-o", tmp_path / "sel.png", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    line = next(ln for ln in res.stdout.splitlines() if ln.startswith("regions:"))
    m = re.match(r"regions: fixed ([\d,]+) \(rings ([\d+,]+)\)  handle ([\d,]+) "
                 r"\(rings ([\d+,]+)\)  free ([\d,]+)  of ([\d,]+) points", line)
    assert m, line
    fixed, handle, free, total = (int(m.group(i).replace(",", "")) for i in (1, 3, 5, 6))
    x = sd.load(scans / "bar.ply").positions[:, 0]
    assert (fixed, handle, total) == (int((x <= 1).sum()), int((x >= 3).sum()), N_BAR)
    assert free == total - fixed - handle
    for group, size in ((2, fixed), (4, handle)):
        rings = [int(v) for v in m.group(group).split("+")]
        assert len(rings) == 3 and all(r > 0 for r in rings) and sum(rings) < size
    assert not (tmp_path / "out").exists()  # select writes no model
    deform = run("deform", path, cwd=tmp_path)
    assert deform.returncode == 0, deform.stderr
    assert line in deform.stdout.splitlines()  # deform prints the same counts
    from PIL import Image

    image = np.asarray(Image.open(tmp_path / "sel.png").convert("RGB")).astype(int)
    # half the width, plus the label strip: 18 px a line, the legend wrapped to the panel
    assert image.shape[1:] == (160, 3) and image.shape[0] - 160 in (18, 36, 54, 72)
    assert stat.S_IMODE((tmp_path / "sel.png").stat().st_mode) == 0o644
    blue = (image[..., 2] > image[..., 0] + 60).sum()
    orange = (image[..., 0] > image[..., 2] + 60).sum()
    assert blue > 50 and orange > 50  # both regions visible in their colours


def test_select_errors_are_one_line(scans, tmp_path):
    cfg = base_config(scans)
    cfg["regions"]["handle"] = [{"box": {"min": [10, 10, 10], "max": [11, 11, 11]}}]
    path = write_config(tmp_path, cfg)
    one_error_line(run("select", path, cwd=tmp_path), 2, ["edit.yaml", "regions.handle"])
    ok = write_config(tmp_path, base_config(scans), "ok.yaml")
    one_error_line(run("select", ok, "-o", tmp_path / "ok.yaml", cwd=tmp_path), 2, ["-o"])
    link = _hardlink(scans / "bar.ply", tmp_path / "link.png")
    one_error_line(run("select", ok, "-o", link, cwd=tmp_path), 2, ["input model"])


# ---------------------------------------------------------------- 6. rough edges

def test_normals_keep_their_input_length(scans, tmp_path):
    cfg = base_config(scans)
    cfg["input"] = str(scans / "long_normals.ply")
    path = write_config(tmp_path, cfg)
    res = run("deform", path, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    src = sd.load(scans / "long_normals.ply")
    out = sd.load(tmp_path / "out" / "bent.ply")
    before = np.linalg.norm(src.normals, axis=1)
    after = np.linalg.norm(out.normals, axis=1)
    moved = np.linalg.norm(out.positions - src.positions, axis=1) > 1e-6
    assert moved.sum() > N_BAR // 4 and (before > 6).sum() > N_BAR // 4
    np.testing.assert_allclose(after, before, rtol=1e-5)
    # and the direction did change where the points moved (the edit rotates the handle)
    cos = np.sum(out.normals * src.normals, axis=1) / (before * after)
    assert (cos[moved] < 0.999).sum() > N_BAR // 10


def test_outputs_get_a_normal_writes_mode(scans, tmp_path):
    """Images and models alike: the mode open(path, "w") would leave (0666 less the umask for
    a new file; an existing file keeps its own)."""
    old = os.umask(0o077)
    try:
        res = run("render", scans / "bar.ply", "-o", tmp_path / "r.png", "--size", "64x64",
                  cwd=tmp_path)
        model = sd.save(sd.load(scans / "bar.ply"), tmp_path / "m.ply")
    finally:
        os.umask(old)
    assert res.returncode == 0, res.stderr
    assert stat.S_IMODE((tmp_path / "r.png").stat().st_mode) == 0o600
    assert stat.S_IMODE(model.stat().st_mode) == 0o600
    os.chmod(tmp_path / "r.png", 0o640)
    res = run("render", scans / "bar.ply", "-o", tmp_path / "r.png", "--size", "64x64",
              cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert stat.S_IMODE((tmp_path / "r.png").stat().st_mode) == 0o640
    res = run("render", scans / "bar.ply", "-o", tmp_path / "new.png", "--size", "64x64",
              cwd=tmp_path)
    assert stat.S_IMODE((tmp_path / "new.png").stat().st_mode) == 0o666 & ~_umask()
    assert not [p.name for p in tmp_path.iterdir() if ".tmp" in p.name]


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def test_frame_paths_keep_normal_lengths():
    """The whole-array and the cache-blocked per-frame paths both keep each normal's length."""
    from splatdeform.deform.arrays import deform_frame, jacobians, transform_normals

    rng = np.random.default_rng(5)
    n, k = 500, 4
    values = rng.normal(size=(n, k))
    gradients = rng.normal(scale=0.1, size=(n, k, 3))
    delta = rng.normal(scale=0.3, size=(k, 3))
    normals = rng.normal(size=(n, 3))
    normals *= rng.uniform(0.5, 7.0, size=(n, 1)) / np.linalg.norm(normals, axis=1, keepdims=True)
    whole = transform_normals(jacobians(gradients, delta), normals)
    _, blocked = deform_frame(rng.normal(size=(n, 3)), normals, values, gradients, delta,
                              chunk=64)
    length = np.linalg.norm(normals, axis=1)
    np.testing.assert_allclose(np.linalg.norm(whole, axis=1), length, rtol=1e-12)
    np.testing.assert_allclose(blocked, whole, rtol=1e-10, atol=1e-12)


def test_select_several_handles_same_line_as_deform(scans, tmp_path):
    cfg = base_config(scans)
    transform = cfg.pop("handle")
    del cfg["regions"]["handle"]
    cfg["regions"]["fixed"] = [{"box": {"min": [1.7, -1, -1], "max": [2.3, 1, 1]}}]
    cfg["handles"] = [{"region": [{"box": {"min": [3.2, -1, -1], "max": [5, 1, 1]}}], **transform},
                      {"region": [{"box": {"min": [-1, -1, -1], "max": [0.8, 1, 1]}}],
                       **transform}]
    path = write_config(tmp_path, cfg)
    sel = run("select", path, cwd=tmp_path)
    assert sel.returncode == 0, sel.stderr
    line = sel.stdout.splitlines()[0]
    x = sd.load(scans / "bar.ply").positions[:, 0]
    moving = int(((x >= 3.2) | (x <= 0.8)).sum())
    assert line.startswith(f"regions: fixed {int(((x >= 1.7) & (x <= 2.3)).sum()):,} (rings ")
    assert f"handles {moving:,} (rings " in line
    deform = run("deform", path, cwd=tmp_path)
    assert deform.returncode == 0, deform.stderr
    assert deform.stdout.splitlines()[0] == line
