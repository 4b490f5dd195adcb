"""The order SOG stores splats in (``save.sog_order`` / ``convert --sog-order``): Morton order by
default, the very order splat-transform 3.7.0 writes (checked against its file), which makes a
scene stored in random order 1.14x smaller; ``keep`` keeps the given order; an unchanged
re-save writes the file as it was read; the other splat writers keep the order."""

from __future__ import annotations

import io
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import bar_edit
from helpers import one_error_line, run_cli
from PIL import Image
from scipy.spatial import cKDTree

from data_tools import splat_transform
from data_tools.synth import gaussian_bar
from splatdeform.edit.run import run_edit
from splatdeform.errors import InputError
from splatdeform.io import load, save
from splatdeform.io.sog_order import morton_order, order


@pytest.fixture(autouse=True)
def _quiet():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the lossy writers' notes
        yield


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """20k splats on a bar, stored in random order (float64 positions), SH degree 0."""
    return save(gaussian_bar(20_000, seed=5), tmp_path_factory.mktemp("sog_order") / "bar.ply")


@pytest.fixture(scope="module")
def sh_scene(tmp_path_factory) -> Path:
    """3000 splats on a bar in random order, SH degree 1 (a palette and its labels)."""
    return save(gaussian_bar(3000, sh_degree=1, seed=6),
                tmp_path_factory.mktemp("sog_order_sh") / "bar.ply")


def _rows_of(decoded: np.ndarray, original: np.ndarray) -> np.ndarray:
    """(N,) the original row nearest to each decoded position."""
    return cKDTree(original).query(decoded)[1]


def _pixels(path: Path) -> dict[str, np.ndarray]:
    with zipfile.ZipFile(path) as z:
        return {n: np.asarray(Image.open(io.BytesIO(z.read(n))).convert("RGBA")).reshape(-1, 4)
                for n in z.namelist() if n.endswith(".webp")}


def test_default_is_splat_transforms_morton_order(scene, tmp_path) -> None:
    try:
        splat_transform.install()
    except splat_transform.OracleMissing as exc:
        pytest.fail(f"the splat-transform oracle is required: {exc}")
    original = load(scene).positions
    ours = load(save(load(scene), tmp_path / "ours.sog")).positions
    theirs_file = tmp_path / "theirs.sog"
    splat_transform.run("-w", "-q", "-g", "cpu", str(scene), str(theirs_file))
    theirs = load(theirs_file).positions
    # row for row the same splat (16-bit positions: a code apart at most; neighbours on this
    # bar are ~0.02 apart, so one swapped pair fails)
    assert np.abs(ours - theirs).max() < 2e-3
    np.testing.assert_array_equal(_rows_of(ours, original), morton_order(original))


def test_keep_keeps_the_order(scene, tmp_path) -> None:
    original = load(scene).positions
    with order("keep"):
        kept = load(save(load(scene), tmp_path / "kept.sog")).positions
    np.testing.assert_array_equal(_rows_of(kept, original), np.arange(len(original)))
    moved = load(save(load(scene), tmp_path / "morton.sog")).positions
    assert (_rows_of(moved, original) != np.arange(len(original))).mean() > 0.9
    assert (tmp_path / "morton.sog").stat().st_size < (tmp_path / "kept.sog").stat().st_size


@pytest.mark.parametrize("ext", [".spz", ".splat", ".compressed.ply", ".glb"])
def test_other_splat_writers_keep_the_order(scene, tmp_path, ext) -> None:
    """(.ksplat is read only here.) Row for row within each format's position step (the bar is
    4 long: a row out of place is off by up to 4)."""
    original = load(scene).positions
    back = load(save(load(scene), tmp_path / f"x{ext}")).positions
    assert np.abs(back - original).max() < 0.01, ext


@pytest.mark.parametrize("how", [None, "keep"])
def test_unchanged_resave_writes_the_file_as_read(sh_scene, tmp_path, how) -> None:
    with order(how):
        first = save(load(sh_scene), tmp_path / "first.sog")
        second = save(load(first), tmp_path / "second.sog")
    assert second.read_bytes() == first.read_bytes()


def test_edited_scene_is_reordered_and_untouched_splats_keep_their_codes(sh_scene, tmp_path):
    """An edited SOG is stored in Morton order of its new positions; the untouched splats keep
    every code, as in the input's order (test_splat_formats' row-for-row check)."""
    first = save(load(sh_scene), tmp_path / "first.sog")
    model = load(first).copy()
    n = model.n_points
    moved = np.zeros(n, dtype=bool)
    moved[::20] = True
    model.positions[moved] *= 0.9   # inside the input's range
    with order("keep"):
        kept = save(model, tmp_path / "kept.sog")
    default = save(model, tmp_path / "morton.sog")
    perm = morton_order(model.positions)
    assert not np.array_equal(perm, np.arange(n))
    a, b = _pixels(kept), _pixels(default)
    for name in ("means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp"):
        np.testing.assert_array_equal(b[name][:n], a[name][:n][perm], err_msg=name)
    untouched = ~moved[perm]
    np.testing.assert_array_equal(b["shN_labels.webp"][:n][untouched],
                                  a["shN_labels.webp"][:n][perm][untouched])
    np.testing.assert_array_equal(load(default).positions, load(kept).positions[perm])


def test_morton_order_edge_cases() -> None:
    for p in (np.zeros((0, 3)), np.ones((1, 3)), np.ones((500, 3)),
              np.array([[0, 0, 0], [np.nan, 0, 0], [1, 1, 1]])):
        np.testing.assert_array_equal(morton_order(p), np.arange(len(p)))
    rng = np.random.default_rng(2)
    # a dense cluster (one top-level cell) is ordered again inside its own box
    p = np.concatenate([rng.uniform(-100, 100, (300, 3)), rng.uniform(0, 1e-6, (2000, 3))])
    perm = morton_order(p)
    np.testing.assert_array_equal(np.sort(perm), np.arange(len(p)))
    cluster = p[perm][np.isin(perm, np.arange(300, 2300))]
    steps = np.linalg.norm(np.diff(cluster, axis=0), axis=1)
    assert np.median(steps) < 0.1e-6   # neighbours in space, not the input's random order
    with pytest.raises(InputError, match="sog_order"):
        with order("hilbert"):
            pass


def test_cli_flag_and_config_key(scene, tmp_path) -> None:
    original = load(scene).positions
    res = run_cli("convert", scene, tmp_path / "kept.sog", "--sog-order", "keep")
    assert res.returncode == 0, res.stderr
    kept = load(tmp_path / "kept.sog").positions
    np.testing.assert_array_equal(_rows_of(kept, original), np.arange(len(original)))
    res = run_cli("convert", scene, tmp_path / "x.sog", "--sog-order", "hilbert")
    assert res.returncode == 2 and "--sog-order" in res.stderr
    assert not (tmp_path / "x.sog").exists()
    cfg = bar_edit(input=str(scene), output="edit.sog", save={"sog_order": "keep"})
    out = run_edit(cfg, tmp_path).output
    assert load(out).n_points == len(original)
    edited = load(out).positions   # the bar's fixed quarter did not move: still row for row
    fixed = original[:, 0] <= original[:, 0].min() + 0.2 * np.ptp(original[:, 0])
    np.testing.assert_allclose(edited[fixed], original[fixed], atol=2e-3)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(bar_edit(input=str(scene), output="bad.sog",
                                           save={"sog_order": "hilbert"})))
    res = run_cli("deform", bad, cwd=tmp_path)
    one_error_line(res, 2, ["save.sog_order"])
    assert not (tmp_path / "bad.sog").exists()
