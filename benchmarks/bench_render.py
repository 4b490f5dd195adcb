"""Splat rendering throughput: plain vs shader-deformed, and CPU apply + upload vs shader.

    python benchmarks/bench_render.py [--points 1000000] [--size 512] [--repeats 3]

Renders a seeded synthetic surfel scan (data_tools.synth.bumpy_bar) with a random smooth k = 4
basis. Ratios are measured in one run on one device; with Mesa llvmpipe (software GL on the
CPU) the absolute numbers say nothing about a GPU.
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
from splatdeform.frame import displace, jacobians, transform_axes, transform_normals  # noqa: E402
from splatdeform.render.camera import frame_points  # noqa: E402
from splatdeform.render.context import describe  # noqa: E402
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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)

    model = bumpy_bar(args.points, seed=0)
    values, gradients = smooth_basis(model.positions)
    rng = np.random.default_rng(1)
    delta_c = rng.normal(size=(4, 3)) * 0.02 * model.diagonal()
    renderer = Renderer((args.size, args.size))
    gpu = renderer.upload(model, values, gradients)
    geom = splat_geometry(model)
    camera = frame_points(
        [model.positions, displace(model.positions, values.astype(np.float64), delta_c)]
    )
    n = model.n_points

    # CPU per-frame path: apply in float32, rewrite a second model's attribute buffer, plain
    # draw of that deformed geometry (the same image as the shader path)
    cpu_gpu = renderer.upload(model)
    pos32 = (model.positions - gpu.origin).astype(np.float32)
    normals32, axes32 = geom.normals, geom.axes
    delta32 = delta_c.astype(np.float32)
    attrs = np.empty((n, 12), dtype=np.float32)

    def cpu_apply() -> None:
        jac = jacobians(gradients, delta32)
        attrs[:, 0:3] = displace(pos32, values, delta32)
        attrs[:, 3:6] = transform_normals(jac, normals32)
        attrs[:, 6:12] = transform_axes(jac, axes32).reshape(n, 6)

    def upload() -> None:
        cpu_gpu.buffers[0].write(attrs.tobytes())
        renderer.ctx.finish()

    cpu_apply()
    upload()
    t = interleaved_best(
        {
            "plain_undeformed": lambda: renderer.draw(gpu, camera, plain=True),
            "plain": lambda: renderer.draw(cpu_gpu, camera),
            "shader": lambda: renderer.draw(gpu, camera, delta_c),
            "apply": cpu_apply,
            "upload": upload,
        },
        args.repeats,
    )
    plain_undeformed, plain, shader = t["plain_undeformed"], t["plain"], t["shader"]
    apply_s, upload_s = t["apply"], t["upload"]
    cpu_total = apply_s + upload_s + plain
    shader_overhead = shader - plain

    print(f"splat rendering, {n:,} splats, {args.size}x{args.size}, MSAA 4x")
    print(f"device: {describe()}")
    print("NOTE: llvmpipe is Mesa's software rasteriser on the CPU (2 cores here): the vertex")
    print("      stage runs on the same cores as numpy; GPU numbers would differ completely.")
    print("      Times are the best of --repeats interleaved runs; other load on the machine")
    print("      still makes differences below ~20 % noise (check `uptime`).")
    rows = [
        ("plain render, undeformed model", plain_undeformed),
        ("plain render, CPU-deformed geometry", plain),
        ("shader-deformed render", shader),
        ("  shader deformation (deformed - plain)", shader_overhead),
        ("CPU apply (numpy float32: P, J, n, u, v)", apply_s),
        (f"upload ({attrs.nbytes // 2**20} MiB attribute rewrite)", upload_s),
        ("CPU apply + upload + plain render", cpu_total),
    ]
    print(f"{'path':44s} {'ms/frame':>10s} {'Msplats/s':>10s}")
    for name, seconds in rows:
        rate = (
            f"{n / seconds / 1e6:10.2f}"
            if seconds > 0 and not name.startswith(" ")
            else " " * 9 + "-"
        )
        print(f"{name:44s} {seconds * 1e3:10.1f} {rate}")
    print(
        f"ratio shader-deformed / plain (same deformed image): {shader / plain:5.2f}x"
        "  (target <= 1.3x)"
    )
    print(f"ratio CPU apply+upload+render / shader-deformed:     {cpu_total / shader:5.2f}x")
    gpu.release()
    cpu_gpu.release()
    renderer.release()


if __name__ == "__main__":
    main()
