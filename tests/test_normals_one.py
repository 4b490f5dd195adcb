"""One normal estimator: splatdeform.deform.normals.pca_normals (local PCA over kNN), used by
the renderer for models without normals and by estimate_normals (which only orients them)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from data_tools.synth import bumpy_bar, sphere
from splatdeform.deform.normals import estimate_normals, pca_normals
from splatdeform.model import PointModel
from splatdeform.render.splats import PCA_NEIGHBORS, splat_geometry


def _abs_cos(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(np.einsum("ij,ij->i", a, b))


@pytest.mark.parametrize("seed", [0, 1])
def test_pca_normals_plane(seed: int) -> None:
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    st = rng.uniform(-5, 5, size=(3000, 2))
    pts = st[:, :1] * u + st[:, 1:] * v + [4.0e5, -3.0e6, 120.0]  # UTM-like offset
    est = pca_normals(pts, 12)
    assert est.shape == (3000, 3) and est.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(est, axis=1), 1.0, atol=1e-12)
    assert _abs_cos(est, np.tile(normal, (3000, 1))).min() > 1 - 1e-6


def test_pca_normals_sphere_and_chunks(monkeypatch) -> None:
    s = sphere(5000, radius=3.0, seed=4)
    est = pca_normals(s.positions, 16)
    ang = np.degrees(np.arccos(np.clip(_abs_cos(est, s.normals), 0, 1)))
    assert np.percentile(ang, 99) < 5 and ang.max() < 10
    # chunking is memory bookkeeping only: small chunks give the same normals
    import splatdeform.deform.normals as mod

    monkeypatch.setattr(mod, "PCA_CHUNK", 777)
    np.testing.assert_array_equal(mod.pca_normals(s.positions, 16), est)


def test_pca_normals_tiny_inputs() -> None:
    assert pca_normals(np.zeros((0, 3)), 12).shape == (0, 3)
    np.testing.assert_array_equal(pca_normals(np.zeros((2, 3)), 12), [[0, 0, 1], [0, 0, 1]])
    three = pca_normals(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), 12)
    assert _abs_cos(three, np.tile([0.0, 0, 1], (3, 1))).min() > 1 - 1e-12


def test_estimate_normals_consistent_on_closed_surface() -> None:
    bar = bumpy_bar(6000, seed=2)  # closed: a bumpy cylinder with caps, outward normals
    model = PointModel(positions=bar.positions.copy(), kind="cloud")
    est = estimate_normals(model, k=16, orient="consistent")
    assert est.kind == "oriented_cloud" and model.normals is None
    np.testing.assert_allclose(np.linalg.norm(est.normals, axis=1), 1.0, atol=1e-9)
    dots = np.einsum("ij,ij->i", est.normals, bar.normals)
    # one global sign; the cap rims (sharp edges) may tilt, but never flip relative to the rest
    sign = 1.0 if np.median(dots) > 0 else -1.0
    assert (sign * dots > 0).mean() > 0.995
    assert np.percentile(np.degrees(np.arccos(np.clip(np.abs(dots), 0, 1))), 90) < 10


def test_renderer_and_estimate_normals_agree() -> None:
    s = sphere(3000, radius=1.5, seed=9)
    model = PointModel(positions=s.positions + [50.0, 0.0, -20.0], kind="cloud")
    rendered = splat_geometry(model).normals.astype(np.float64)  # float32 upload
    estimated = estimate_normals(model, k=PCA_NEIGHBORS, orient="outward").normals
    assert _abs_cos(rendered, estimated).min() > 1 - 1e-6


def test_importing_normals_imports_no_open3d() -> None:
    code = ("import sys\nimport splatdeform.deform.normals as n\n"
            "import numpy as np\n"
            "from splatdeform.model import PointModel\n"
            "pts = np.random.default_rng(0).normal(size=(50, 3))\n"
            "n.estimate_normals(PointModel(positions=pts), orient='outward')\n"
            "print('open3d' in sys.modules)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.stdout.strip() == "False", res.stdout + res.stderr
