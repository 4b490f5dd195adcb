"""``splatdeform convert``: formats, the whole-scene similarity in splat-transform's convention
(checked against the pinned 3.7.0), streaming within a memory budget, one-line errors."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import shared_file
from helpers import make_las, one_error_line, run_cli
from sh_scene import TILE, sh_tile

from data_tools import splat_transform
from splatdeform.cli import main
from splatdeform.conversion import convert, similarity, transform_model
from splatdeform.io import load, save
from splatdeform.io.splats import LossyWriteWarning


def _quiet(argv: list[str]) -> int:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LossyWriteWarning)
        return main(argv)


@pytest.mark.parametrize("angles", ["0,0,37", "30,-40,75"])
@pytest.mark.parametrize("source", ["shared", "with_sh"])
def test_rotate_euler_equals_splat_transform(tmp_path, oracle, angles, source):
    src = shared_file(TILE) if source == "shared" else sh_tile(tmp_path / "sh.ply")
    theirs, ours = tmp_path / "theirs.ply", tmp_path / "ours.ply"
    splat_transform.run("-w", "-q", str(src), "-r", angles, "-s", "1.5", "-t", "1,-2,3",
                        str(theirs))
    assert main(["convert", str(src), str(ours), f"--rotate-euler={angles}", "--scale", "1.5",
                 "--translate=1,-2,3"]) == 0
    a, b = load(theirs), load(ours)
    assert a.n_points == b.n_points == load(src).n_points
    assert np.abs(a.positions - b.positions).max() <= 1e-5
    assert np.abs(a.gaussians.sh_rest - b.gaussians.sh_rest).max() <= 1e-5
    assert np.abs(a.gaussians.scale_log - b.gaussians.scale_log).max() <= 1e-5
    qa, qb = (g.rotation / np.linalg.norm(g.rotation, axis=1, keepdims=True)
              for g in (a.gaussians, b.gaussians))
    assert np.minimum(np.abs(qa - qb).max(1), np.abs(qa + qb).max(1)).max() <= 1e-5
    if source == "with_sh":   # the rotation really turned the colour
        assert np.abs(b.gaussians.sh_rest - load(src).gaussians.sh_rest).max() > 0.01


def test_transform_is_an_exact_similarity():
    model = load(shared_file(TILE))
    sim = similarity((10.0, 20.0, 30.0), 2.0, (0.5, 0.25, -1.0))
    out = transform_model(model, sim)
    want = model.positions.astype(np.float64) @ (2.0 * sim.rotation).T + sim.translation
    assert np.abs(out.positions - want).max() < 1e-5
    assert np.allclose(out.gaussians.scale_log, model.gaussians.scale_log + np.log(2.0),
                       atol=1e-6)
    assert np.allclose(np.linalg.norm(out.gaussians.rotation, axis=1),
                       np.linalg.norm(model.gaussians.rotation, axis=1), atol=1e-5)
    assert transform_model(model, similarity()) is model


# the fields each format gives back exactly (glTF stores linear scales, unit quaternions and
# alpha: float32 rounding there; LAS coordinates to their 1e-8 scale)
ALL = ("scale_log", "rotation", "opacity", "sh_dc", "sh_rest")
EXACT = {".ply": (True, ALL), ".glb": (True, ("sh_dc", "sh_rest")),
         ".gltf": (True, ("sh_dc", "sh_rest")), ".las": (True, ALL), ".laz": (True, ALL),
         ".pcd": (True, ()), ".xyz": (True, ()), ".splat": (True, ()),
         ".compressed.ply": (False, ()), ".spz": (False, ()), ".sog": (False, ())}


@pytest.mark.parametrize("ext", list(EXACT))
def test_round_trip_through_each_format(tmp_path, ext):
    src = shared_file(TILE)
    mid, back = tmp_path / f"mid{ext}", tmp_path / "back.ply"
    assert _quiet(["convert", str(src), str(mid)]) == 0
    assert _quiet(["convert", str(mid), str(back), "--drop-nonfinite"]) == 0
    a, b = load(src), load(back)
    assert b.n_points == a.n_points
    positions, fields = EXACT[ext]
    if positions:
        tol = 1e-8 if ext in (".las", ".laz") else 1e-10
        assert np.abs(a.positions - b.positions).max() <= tol
    for name in fields:
        assert np.array_equal(getattr(a.gaussians, name), getattr(b.gaussians, name)), name


def test_no_transform_is_load_and_save_byte_for_byte(tmp_path):
    src = shared_file(TILE)
    out, ref = tmp_path / "out.ply", tmp_path / "ref.ply"
    assert main(["convert", str(src), str(out)]) == 0
    save(load(src), ref)
    assert out.read_bytes() == ref.read_bytes() == src.read_bytes()


def test_streamed_convert_equals_in_memory(tmp_path, capsys):
    src = sh_tile(tmp_path / "sh.ply")
    whole, streamed = tmp_path / "whole.ply", tmp_path / "streamed.ply"
    args = ["--rotate-euler=15,25,-35", "--scale", "0.5", "--translate=1,2,3"]
    assert main(["convert", str(src), str(whole), *args]) == 0
    assert main(["convert", str(src), str(streamed), *args, "--memory-budget", "64MB"]) == 0
    assert "streamed" in capsys.readouterr().out
    assert streamed.read_bytes() == whole.read_bytes()


def test_las_streams_and_moves_its_coordinates(tmp_path):
    src = make_las(tmp_path / "in.las", n=4000)
    whole, streamed = tmp_path / "whole.las", tmp_path / "streamed.las"
    assert main(["convert", str(src), str(whole), "--translate=10,20,30"]) == 0
    assert convert(src, streamed, similarity(None, None, (10, 20, 30)),
                   budget=64 << 20) == "stream"
    a, b, c = load(src), load(whole), load(streamed)
    # splat-transform's frame: x and y of a translation change sign in the file's frame
    assert np.allclose(b.positions - a.positions, [-10, -20, 30], atol=0.011)
    assert np.allclose(c.positions, b.positions, atol=0.011)


def test_over_an_explicit_budget_unstreamable_is_refused(tmp_path):
    src = shared_file(TILE)
    res = run_cli("convert", str(src), str(tmp_path / "out.sog"), "--memory-budget", "64MB")
    line = one_error_line(res, 2, needles=("memory budget",))
    assert "same format" in line
    assert not (tmp_path / "out.sog").exists()


@pytest.mark.parametrize("args, needle", [
    (["IN", "IN"], "is the input"),
    (["IN", "OUT.xyzw"], "unknown extension"),
    (["IN", "OUT.ply", "--rotate-euler", "1,2"], "--rotate-euler"),
    (["IN", "OUT.ply", "--scale", "0"], "--scale"),
    (["IN", "OUT.ply", "--translate=1,nan,2"], "--translate"),
    (["IN", "OUT.ply", "--sog-quality", "best"], "--sog-quality"),
])
def test_bad_usage_is_one_line(tmp_path, args, needle):
    src = shared_file(TILE)
    argv = [str(src) if a == "IN" else str(tmp_path / a) if a.startswith("OUT") else a
            for a in args]
    res = run_cli("convert", *argv)
    one_error_line(res, 2, needles=(needle,))
    assert list(tmp_path.iterdir()) == []
