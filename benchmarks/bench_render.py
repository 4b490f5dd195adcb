"""Rendering throughput: 3D Gaussian splats and surfels, plain vs shader-deformed.

    python benchmarks/bench_render.py [--gaussians 1000000] [--surfels 1000000] [--size 512]
                                      [--sh-degree 0] [--repeats 3]

Gaussians: a seeded synthetic scene (points of data_tools.synth.bumpy_bar with random small
anisotropic Gaussians, opacities and SH coefficients of the given degree) and a random smooth
k = 4 basis. "plain" renders the same deformed scene computed on the CPU (positions p', covariances
J Sigma J^T re-factored, SH as stored) with the plain program; "shader-deformed" applies delta C
in the vertex stage. Both include the per-frame depth sort (numpy argsort on the CPU), whose share
is printed. Surfels: the blended two-pass surface splatting, same comparison. Ratios are measured
in one run on one device; with Mesa llvmpipe (software GL on the CPU) the absolute numbers say
nothing about a GPU.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from data_tools.synth import bumpy_bar  # noqa: E402
from splatdeform.deform.arrays import displace, jacobians, transform_axes, transform_normals  # noqa: E402
from splatdeform.model import Gaussians, PointModel  # noqa: E402
from splatdeform.render.camera import frame_points  # noqa: E402
from splatdeform.render.context import describe  # noqa: E402
from splatdeform.render.gaussian_data import covariances  # noqa: E402
from splatdeform.render.renderer import Renderer  # noqa: E402
from splatdeform.render.splats import splat_geometry  # noqa: E402


def smooth_basis(positions: np.ndarray, k: int = 4, seed: int = 0):
    """(N, k) float32 values and (N, k, 3) float32 gradients of seeded random sines."""
    rng = np.random.default_rng(seed)
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    scale = float(np.linalg.norm(hi - lo))
    freq = rng.normal(size=(3, k)) * 3.0
    arg = ((positions - (lo + hi) / 2) / scale) @ freq
    values = 0.5 * np.sin(arg)
    gradients = (0.5 * np.cos(arg))[:, :, None] * freq.T[None] / scale
    return values.astype(np.float32), gradients.astype(np.float32)


def interleaved_best(fns: dict, repeats: int) -> dict:
    """Best (minimum) wall time of each callable, the callables interleaved round-robin so that
    load from other processes hits all of them alike. One warm-up call each."""
    for fn in fns.values():
        fn()
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(repeats):
        for name, fn in fns.items():
            t = time.perf_counter()
            fn()
            best[name] = min(best[name], time.perf_counter() - t)
    return best


def gaussian_scene(n: int, sh_degree: int, seed: int = 0) -> PointModel:
    """n Gaussians on a bumpy bar surface, sized like its sample spacing."""
    bar = bumpy_bar(n, seed=seed)
    rng = np.random.default_rng(seed + 1)
    spacing = np.sqrt(bar.diagonal() ** 2 / n) * 0.5
    scale_log = np.log(spacing * rng.uniform(0.3, 1.0, size=(n, 3))).astype(np.float32)
    rotation = rng.normal(size=(n, 4)).astype(np.float32)
    rest = None
    if sh_degree:
        m = (sh_degree + 1) ** 2 - 1
        rest = (rng.normal(size=(n, 3 * m)) * 0.1).astype(np.float32)
    return PointModel(
        positions=bar.positions, kind="gaussians",
        gaussians=Gaussians(scale_log, rotation, rng.normal(1.0, 1.0, n).astype(np.float32),
                            rng.normal(0.0, 0.8, (n, 3)).astype(np.float32), rest))


def matrix_quaternions(rot: np.ndarray) -> np.ndarray:
    """(N, 3, 3) proper rotations -> (N, 4) quaternions (w, x, y, z)."""
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(rot).as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)


def cpu_deformed_gaussians(model: PointModel, values, gradients, delta_c) -> PointModel:
    """Positions p' and covariances J Sigma J^T on the CPU (eigen-refactored: fine for timing)."""
    g = model.gaussians
    jac = jacobians(gradients.astype(np.float64), delta_c)
    sigma = covariances(g.scale_log, g.rotation)
    sigma = jac @ sigma @ jac.transpose(0, 2, 1)
    w, v = np.linalg.eigh(sigma)
    v[np.linalg.det(v) < 0, :, 0] *= -1
    out = PointModel(positions=displace(model.positions, values.astype(np.float64), delta_c),
                     kind="gaussians",
                     gaussians=Gaussians((0.5 * np.log(np.maximum(w, 1e-30))).astype(np.float32),
                                         matrix_quaternions(v).astype(np.float32), g.opacity,
                                         g.sh_dc, g.sh_rest))
    return out


def print_rows(title: str, n: int, rows: list[tuple[str, float]]) -> None:
    print(title)
    print(f"{'path':60s} {'ms/frame':>10s} {'Msplats/s':>10s}")
    for name, seconds in rows:
        rate = f"{n / seconds / 1e6:10.2f}" if not name.startswith(" ") else " " * 9 + "-"
        print(f"{name:60s} {seconds * 1e3:10.1f} {rate}")


def bench_gaussians(args: argparse.Namespace) -> None:
    model = gaussian_scene(args.gaussians, args.sh_degree)
    values, gradients = smooth_basis(model.positions)
    delta_c = np.random.default_rng(1).normal(size=(4, 3)) * 0.02 * model.diagonal()
    after = cpu_deformed_gaussians(model, values, gradients, delta_c)
    renderer = Renderer((args.size, args.size))
    gpu = renderer.upload(model, values, gradients)
    cpu = renderer.upload(after)
    camera = frame_points([model.positions, after.positions])
    sorts: dict[str, float] = {}

    def shader() -> None:
        renderer.draw(gpu, camera, delta_c)
        sorts["shader"] = gpu.timings["sort"]

    def plain() -> None:
        renderer.draw(cpu, camera)
        sorts["plain"] = cpu.timings["sort"]

    t = interleaved_best({"plain": plain, "shader": shader}, args.repeats)
    n = model.n_points
    print_rows(
        f"3D Gaussian splats, {n:,} splats, SH degree {args.sh_degree}, "
        f"{args.size}x{args.size}, sorted back to front, premultiplied blending",
        n,
        [("plain render of the CPU-deformed scene", t["plain"]),
         ("shader-deformed render", t["shader"]),
         ("  depth sort, shader-deformed (p' = p + B dC, argsort, upload)", sorts["shader"]),
         ("  depth sort, plain (argsort, upload)", sorts["plain"])],
    )
    print(f"ratio shader-deformed / plain: {t['shader'] / t['plain']:5.2f}x  (target <= 1.3x)")
    print(f"depth sort share of the shader-deformed frame: {sorts['shader'] / t['shader']:5.1%}")
    gpu.release()
    cpu.release()
    renderer.release()


def bench_surfels(args: argparse.Namespace) -> None:
    model = bumpy_bar(args.surfels, seed=0)
    values, gradients = smooth_basis(model.positions)
    delta_c = np.random.default_rng(1).normal(size=(4, 3)) * 0.02 * model.diagonal()
    geom = splat_geometry(model)
    jac = jacobians(gradients.astype(np.float64), delta_c)
    after = model.copy()
    after.positions = displace(model.positions, values.astype(np.float64), delta_c)
    after.normals = transform_normals(jac, geom.normals.astype(np.float64))
    after.axes = transform_axes(jac, geom.axes.astype(np.float64))
    after.radius = None
    renderer = Renderer((args.size, args.size))
    gpu = renderer.upload(model, values, gradients)
    cpu = renderer.upload(after, fill_holes=False)
    camera = frame_points([model.positions, after.positions])
    t = interleaved_best({"plain": lambda: renderer.draw(cpu, camera),
                          "shader": lambda: renderer.draw(gpu, camera, delta_c),
                          "opaque": lambda: renderer.draw(gpu, camera, delta_c, blend=False)},
                         args.repeats)
    n = model.n_points
    print_rows(
        f"surfels, {n:,} splats, {args.size}x{args.size}, two-pass surface splatting",
        n,
        [("plain render of the CPU-deformed surfels", t["plain"]),
         ("shader-deformed render", t["shader"]),
         ("shader-deformed, opaque discs (one pass, MSAA 4x)", t["opaque"])],
    )
    print(f"ratio shader-deformed / plain: {t['shader'] / t['plain']:5.2f}x  (target <= 1.3x)")
    gpu.release()
    cpu.release()
    renderer.release()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--surfels", type=int, default=1_000_000)
    parser.add_argument("--sh-degree", type=int, default=0, choices=(0, 1, 2, 3))
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    print(f"device: {describe()}")
    print("NOTE: llvmpipe is Mesa's software rasteriser on the CPU: the vertex stage and the")
    print("      blending run on the same cores as numpy; GPU numbers differ completely.")
    print("      Times are the best of --repeats interleaved runs (check `uptime` for load).")
    if args.gaussians:
        bench_gaussians(args)
    if args.surfels:
        bench_surfels(args)


if __name__ == "__main__":
    main()
