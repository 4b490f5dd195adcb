"""Fixtures and reference helpers shared by several test modules (no test module imports
another): an independent B-spline basis and a curve on the bunny (curve tests), the streamed
edit and its in-memory comparison (stream, signal and Dask tests), and the running editor verb
(editor tests). Small generic helpers (the CLI runner, error lines, peak memory) are in
:mod:`helpers`."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from conftest import bar_edit
from scipy.spatial import cKDTree

import splatdeform as sd
from splatdeform.io.ply_format import read_ply
from splatdeform.model import Gaussians, PointModel

# ------------------------------------------------------------------------------- curves

def cox_de_boor(knots: np.ndarray, degree: int, t: np.ndarray) -> np.ndarray:
    """Independent B-spline basis (len(t), k) by the Cox-de Boor recursion, right end closed."""
    k = knots.size - degree - 1
    t = np.asarray(t, dtype=np.float64)
    n0 = knots.size - 1
    basis = np.zeros((t.size, n0))
    for i in range(n0):
        basis[:, i] = (knots[i] <= t) & (t < knots[i + 1])
    last = max(i for i in range(n0) if knots[i] < knots[i + 1])
    basis[t >= knots[-1], last] = 1.0
    for p in range(1, degree + 1):
        nxt = np.zeros((t.size, n0 - p))
        for i in range(n0 - p):
            a = knots[i + p] - knots[i]
            b = knots[i + p + 1] - knots[i + 1]
            left = (t - knots[i]) / a * basis[:, i] if a > 0 else 0.0
            right = (knots[i + p + 1] - t) / b * basis[:, i + 1] if b > 0 else 0.0
            nxt[:, i] = left + right
        basis = nxt
    assert basis.shape[1] == k
    return basis


def bunny_back_curve(model: sd.PointModel) -> tuple[np.ndarray, np.ndarray]:
    """Control points (5, 3) along the bunny's back and their bend (moved_to)."""
    P = model.positions.astype(np.float64)
    diag = model.diagonal()
    zc = 0.5 * (P[:, 2].min() + P[:, 2].max())
    # control points from the model's own points: the highest point near a line along x
    # through the middle of the back (behind the ears, in front of the tail)
    cp = []
    for x in np.linspace(-0.004, 0.036, 5):
        near = np.flatnonzero((np.abs(P[:, 0] - x) < 0.002) & (np.abs(P[:, 2] - zc) < 0.004))
        cp.append(P[near[P[near, 1].argmax()]])
    cp = np.array(cp)
    # bend: the middle three control points move 5% of the diagonal along the surface normal
    tree = cKDTree(P)
    mv = cp.copy()
    for i in (1, 2, 3):
        _, nb = tree.query(cp[i], 40)
        q = P[nb] - P[nb].mean(axis=0)
        normal = np.linalg.eigh(q.T @ q)[1][:, 0]
        normal *= np.sign(normal[1])  # outward on the back = upward
        mv[i] = cp[i] + 0.05 * diag * normal
    return cp, mv


# ---------------------------------------------------------------------------- streaming

def stream_edit() -> dict:
    """The streaming tests' edit of a bar along x (relative units): the handle turned 35
    degrees about its inner end and lifted; no backend key (the default)."""
    return bar_edit({"pivot": [0.75, 0.5, 0.5], "rotate": {"axis": [0, 0, 1], "degrees": 35},
                     "translate": [0, 0.1, 0]}, backend=None)


def vertex(path: Path) -> np.ndarray:
    return read_ply(path).element("vertex").data


def labels_of(data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = data["x"].astype(np.float64)
    u = (x - x.min()) / (x.max() - x.min())
    return u <= 0.25, u >= 0.75


def assert_same_result(mem: Path, streamed: Path, source: Path) -> None:
    """Same header and properties; F and H positions (regions of the ``source`` input)
    bit-exact; free points within the backend's tolerance; every other property equal
    (normals to rounding)."""
    a, b = vertex(mem), vertex(streamed)
    assert a.dtype == b.dtype and a.shape == b.shape
    src_a, src_b = read_ply(mem), read_ply(streamed)
    assert [(e.name, e.count) for e in src_a.elements] == \
        [(e.name, e.count) for e in src_b.elements]
    assert src_a.comments == src_b.comments
    fixed, handle = labels_of(vertex(source))
    pos_a = np.stack([a[c] for c in "xyz"], axis=1)
    pos_b = np.stack([b[c] for c in "xyz"], axis=1)
    rigid = fixed | handle
    assert np.array_equal(pos_a[rigid], pos_b[rigid])
    diag = float(np.linalg.norm(np.ptp(pos_a, axis=0)))
    assert np.abs(pos_a - pos_b).max() <= 1e-6 * diag
    for name in a.dtype.names:
        if name in "xyz":
            continue
        if name in ("nx", "ny", "nz", "radius"):
            assert np.allclose(a[name], b[name], atol=1e-6, rtol=0), name
            assert np.array_equal(a[name][fixed], b[name][fixed]), name
        else:
            assert np.array_equal(a[name], b[name]), name


# ------------------------------------------------------------------------------- editor

def start_editor(path: Path, *args: str) -> tuple[subprocess.Popen, int, str]:
    """The running ``edit`` verb, its port and the URL it printed (with its token)."""
    proc = subprocess.Popen([sys.executable, "-m", "splatdeform.cli", "edit", str(path),
                             "--port", "0", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 60
    for line in proc.stdout:
        if "splatdeform editor: http://" in line:
            url = line.split("splatdeform editor: ")[1].split()[0]
            port = int(url.split("http://127.0.0.1:")[1].split("/")[0])
            return proc, port, url
        if time.time() > deadline:
            break
    proc.kill()
    raise AssertionError("the editor printed no URL")


# ------------------------------------------------------------------------------- splats

def cut(model: PointModel, n: int) -> PointModel:
    """The ``n`` splats nearest the median position (a small real scene)."""
    idx = np.argsort(np.linalg.norm(model.positions - np.median(model.positions, 0), axis=1))[:n]
    g = model.gaussians
    rest = None if g.sh_rest is None else g.sh_rest[idx]
    return PointModel(positions=model.positions[idx], kind="gaussians",
                      gaussians=Gaussians(g.scale_log[idx], g.rotation[idx], g.opacity[idx],
                                          g.sh_dc[idx], rest))


def smooth_basis(positions: np.ndarray, k: int = 4, seed: int = 0):
    """Random but smooth b (N, k) float32 and its exact gradient (N, k, 3) float32."""
    rng = np.random.default_rng(seed)
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    scale = float(np.linalg.norm(hi - lo))
    freq = rng.normal(size=(3, k)) * 3.0
    arg = ((positions - (lo + hi) / 2) / scale) @ freq + rng.uniform(0, 2 * np.pi, size=k)
    amp = rng.uniform(0.2, 1.0, size=k)
    values = amp * np.sin(arg)
    gradients = (amp * np.cos(arg))[:, :, None] * freq.T[None, :, :] / scale
    return values.astype(np.float32), gradients.astype(np.float32)


def to_uint8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(image[:, :, :3] * 255), 0, 255).astype(np.uint8)


def random_splats(n: int, seed: int = 22):
    rng = np.random.default_rng(seed)
    scale_log = rng.uniform(-3.0, -1.0, (n, 3))
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return scale_log, quat


def random_jacobians(n: int, seed: int = 23) -> np.ndarray:
    """Mild (I + 0.1 noise), strong stretches (I + 3 u v^T) and a few folds (det < 0)."""
    rng = np.random.default_rng(seed)
    jac = np.eye(3) + 0.1 * rng.normal(size=(n, 3, 3))
    strong = rng.uniform(size=n) < 0.5
    u = rng.normal(size=(n, 3))
    v = rng.normal(size=(n, 3))
    jac[strong] += 1.5 * np.einsum("ni,nj->nij", u, v)[strong] / 2
    jac[:8] = np.diag([1.2, 0.9, -0.7])  # folded
    return jac
