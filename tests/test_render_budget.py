"""Renders within the memory budget, colour modes, LiDAR views: real files, the real GL
driver, the real CLI. Images are judged by statistics (not blank, the z-up silhouette stands
up, colours of the mode), memory by the peak RSS of a child process."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest
import yaml
from conftest import ROOT, bar_edit
from PIL import Image

from data_tools.lidar import write_lidar
from data_tools.synth import bumpy_bar
from splatdeform import memory
from splatdeform.cli import main
from splatdeform.io import save
from splatdeform.render.colors import point_colors

BACKGROUND = 255


def image(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def covered(img: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels that are not the white background (label strip cut off)."""
    return np.any(img[20:] < BACKGROUND - 8, axis=2)


@pytest.fixture(scope="module")
def scan(tmp_path_factory) -> Path:
    return write_lidar(tmp_path_factory.mktemp("lidar") / "scan.las", 120_000, seed=2)


def tower(path: Path, n: int = 20_000) -> Path:
    """A LAS column 100 m tall and 10 m wide standing on z (class 6), no RGB."""
    rng = np.random.default_rng(1)
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    las = laspy.LasData(header)
    theta = rng.uniform(0, 2 * np.pi, n)
    las.x = 5 * np.cos(theta)
    las.y = 5 * np.sin(theta)
    las.z = rng.uniform(0, 100, n)
    las.classification = np.full(n, 6, dtype=np.uint8)
    las.write(path)
    return path


def test_lidar_defaults_to_z_up(tmp_path: Path, capsys) -> None:
    """A tower standing on +z renders taller than wide by default (LAS is z-up); forced to
    +y up it lies on its side."""
    las = tower(tmp_path / "tower.las")
    assert main(["render", str(las), "-o", str(tmp_path / "z.png"), "--size", "400x400"]) == 0
    assert main(["render", str(las), "-o", str(tmp_path / "y.png"), "--size", "400x400",
                 "--up", "+y"]) == 0
    for name, tall in (("z.png", True), ("y.png", False)):
        mask = covered(image(tmp_path / name))
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        assert mask.mean() > 0.005, name   # not blank
        height, width = np.ptp(rows) + 1, np.ptp(cols) + 1
        assert (height > 2 * width) if tall else (width > height), (name, height, width)
    camera = json.loads((tmp_path / "z.camera.json").read_text())
    assert abs(camera["up"][2]) > 0.9


def test_colour_modes_follow_the_data(scan: Path, tmp_path: Path) -> None:
    """Elevation colours vary with height; classification colours are the ASPRS palette
    (ground brown, buildings red); a colourless LiDAR scan renders by elevation by default."""
    from splatdeform.io import load

    model = load(scan)
    elev = point_colors(model, "elevation", "+z")
    z = model.positions[:, 2]
    low, high = z < np.quantile(z, 0.1), z > np.quantile(z, 0.9)
    assert np.abs(elev[low].mean(axis=0) - elev[high].mean(axis=0)).sum() > 100
    cls = point_colors(model, "classification")
    ground = model.source.element("vertex").data["classification"] == 2
    assert np.all(cls[ground] == (150, 110, 70))
    out = {}
    for mode in ("default", "classification", "intensity"):
        png = tmp_path / f"{mode}.png"
        args = ["render", str(scan), "-o", str(png), "--size", "300x300"]
        assert main(args + ([] if mode == "default" else ["--color", mode])) == 0
        out[mode] = image(png)[20:].reshape(-1, 3)
        assert covered(image(png)).mean() > 0.02, mode
    # classification: mostly ground brown (r > g > b), intensity: grey (r == g == b)
    px = out["classification"][np.any(out["classification"] < 240, axis=1)].astype(int)
    assert np.median(px[:, 0] - px[:, 2]) > 20
    px = out["intensity"][np.any(out["intensity"] < 240, axis=1)].astype(int)
    assert np.median(np.abs(px[:, 0] - px[:, 2])) <= 2
    px = out["default"][np.any(out["default"] < 240, axis=1)].astype(int)
    assert np.std(px[:, 1]) > 15   # the elevation ramp, not one grey


def test_unknown_colour_property_is_one_line(tmp_path: Path, capsys) -> None:
    path = tmp_path / "bar.ply"
    save(bumpy_bar(2_000, seed=1), path)
    assert main(["render", str(path), "-o", str(tmp_path / "a.png"), "--color",
                 "intensity"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "'intensity'" in err and "radius" in err
    assert not (tmp_path / "a.png").exists()


def test_render_beyond_the_budget_samples(tmp_path: Path, capsys) -> None:
    """A 64MB budget cannot hold 400,000 LAS points with their render arrays: a seeded
    view-independent sample renders and the output line says how many."""
    scan = write_lidar(tmp_path / "scan.las", 400_000, seed=4)
    cost = memory.file_cost(scan)
    assert memory.render_points(64 * 2**20, cost) < cost.points
    out = tmp_path / "s.png"
    assert main(["render", str(scan), "-o", str(out), "--memory-budget", "64MB"]) == 0
    text = capsys.readouterr().out
    line = next(x for x in text.splitlines() if "rendered" in x)
    shown = int(line.split("rendered ")[1].split(" of")[0].replace(",", ""))
    assert "of 400,000 points" in line and 0 < shown < 400_000
    assert covered(image(out)).mean() > 0.02
    # the same sample every time (seeded): the image is reproducible
    assert main(["render", str(scan), "-o", str(tmp_path / "t.png"), "--memory-budget",
                 "64MB"]) == 0
    assert np.array_equal(image(out), image(tmp_path / "t.png"))


# VmHWM: this process's own peak (ru_maxrss would carry the forking parent's over exec)
PEAK = """
import sys
from splatdeform.cli import main
code = main(sys.argv[1:])
hwm = next(x for x in open("/proc/self/status") if x.startswith("VmHWM"))
print("PEAK", int(hwm.split()[1]) * 1024, code)
"""


def peak_rss(args: list[str]) -> int:
    out = subprocess.run([sys.executable, "-c", PEAK, *args], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout
    line = next(x for x in out.splitlines() if x.startswith("PEAK"))
    assert line.endswith(" 0"), out
    return int(line.split()[1])


def test_render_bytes_is_a_measured_upper_bound(tmp_path: Path) -> None:
    """memory.render_bytes + the load estimate bound the measured peak of rendering N points
    (above the peak of rendering a tiny file: the interpreter and GL context), within 4x."""
    small = write_lidar(tmp_path / "small.las", 2_000, seed=3)
    big = write_lidar(tmp_path / "big.las", 300_000, seed=3)
    base = peak_rss(["render", str(small), "-o", str(tmp_path / "a.png")])
    peak = peak_rss(["render", str(big), "-o", str(tmp_path / "b.png")])
    measured = peak - base
    cost = memory.file_cost(big)
    estimate = cost.load_bytes + memory.render_bytes(cost.points, cost.record_bytes)
    assert measured > 0
    assert measured <= estimate <= 4 * measured, (measured, estimate)
    # and a sampled render stays within the budget plus the interpreter and GL context
    sampled = peak_rss(["render", str(big), "-o", str(tmp_path / "c.png"), "--memory-budget",
                        "64MB"])
    assert sampled <= 64 * 2**20 + base + 64 * 2**20


def test_streamed_deform_renders_before_after(tmp_path: Path, capsys) -> None:
    """deform --render on an edit that streams (budget below the in-memory estimate): the
    input and output files side by side, each within half the budget."""
    src = tmp_path / "bar.ply"
    save(bumpy_bar(120_000, seed=5), src)
    cfg = bar_edit({"translate": [0, 0.3, 0]}, input=str(src), output="out.ply")
    path = tmp_path / "edit.yaml"
    path.write_text(yaml.safe_dump(cfg))
    png = tmp_path / "ba.png"
    assert main(["deform", str(path), "--memory-budget", "64MB", "--render", str(png),
                 "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "of 120,000 points (memory budget)" in text and (tmp_path / "out.ply").exists()
    img = image(png)
    half = img.shape[1] // 2
    left, right = covered(img[:, :half]), covered(img[:, half:])
    assert left.mean() > 0.01 and right.mean() > 0.01
    # the lifted (right) end: the after panel's silhouette there reaches higher
    end = slice(int(0.7 * left.shape[1]), None)
    top = [np.flatnonzero(m[:, end].any(axis=1))[0] for m in (left, right)]
    assert top[1] < top[0] - 10, top


def test_point_size_adapts_to_the_sampled_density() -> None:
    """Splat radii follow the density drawn: a quarter of the points of a plane get discs about
    twice as wide (surface density), from a subsample's spacing alone."""
    from splatdeform.render.splats import knn_spacing, sampled_spacing

    pts = np.random.default_rng(0).uniform(0, 1, (400_000, 3)) * (1, 1, 0)
    full = sampled_spacing(pts, sample=50_000)
    quarter = sampled_spacing(pts[::4], sample=50_000)
    assert np.ptp(full) == 0 and full.shape == (400_000,)
    assert 1.8 < quarter[0] / full[0] < 2.2
    exact = float(np.median(knn_spacing(pts[::8])))   # the per-point estimate agrees
    assert 0.85 < sampled_spacing(pts[::8], sample=20_000)[0] / exact < 1.15


def test_sampled_render_drops_nonfinite_points(tmp_path: Path, capsys) -> None:
    """A scan over the render budget with NaN coordinates: the sample refuses them with one line
    as a whole load does, and ``--drop-nonfinite`` renders the sample without them."""
    from plyfile import PlyData

    path = tmp_path / "nan.ply"
    save(bumpy_bar(400_000, seed=5), tmp_path / "clean.ply")
    ply = PlyData.read(str(tmp_path / "clean.ply"), mmap=False)
    ply["vertex"].data["x"][::97] = np.nan   # every sample meets some
    ply.write(str(path))
    cost = memory.file_cost(path)
    assert memory.render_points(64 * 2**20, cost) < cost.points
    out = tmp_path / "n.png"
    assert main(["render", str(path), "-o", str(out), "--memory-budget", "64MB"]) == 2
    err = capsys.readouterr().err
    assert "NaN" in err and err.count("\n") == 1 and not out.exists()
    assert main(["render", str(path), "-o", str(out), "--memory-budget", "64MB",
                 "--drop-nonfinite"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if "rendered" in x)
    assert "of 400,000 points" in line
    assert covered(image(out)).mean() > 0.02
