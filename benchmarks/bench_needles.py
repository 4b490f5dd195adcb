"""Needles of deformed 3D Gaussian splats per ``gaussians.covariance`` mode (issue 22), and
the PSNR of the result against a subdivided reference (issue 37, ``--psnr``).

    python benchmarks/bench_needles.py [--scenes guitar,tile,bar] [--images docs/images]
    python benchmarks/bench_needles.py --psnr guitar:75,gbar:90 [--images docs/images]

``--psnr``: the reference subdivides every splat into 8 children (offsets +-0.6 sigma along its
principal axes, child sigma 0.8x: the second moments match; same opacity, colour and SH), each
deformed at its own centre in ``jacobian`` mode (fixed children stay, handle children get the
handle's matrix). Rendered at 800x800 from the camera framing the default result, front
(azimuth 0) and side (azimuth 90), elevation 0: PSNR over the whole image and masked to the
pixels that differ from the background in either image. The floor is the rest-state PSNR of
the subdivided scene against the original. Rows: ``limited`` + ``split: auto`` (the edit
default), ``limited`` unsplit, ``jacobian`` unsplit and split. ``gbar`` is
``data_tools.synth.gaussian_bar`` (20,000 splats).

A needle is a splat whose anisotropy (largest / smallest axis) grew by more than 4x. Each scene
(the shared guitar and SH-3 tile, and a generated bar of round splats) gets one fit (fixed: the
first 40 % along its longest axis; handle: the last 40 %) and three strong edits of the handle:
bends of 45 and 90 degrees about an axis across it, and a drag of 30 % of the scene's size
across the longest axis. Every mode deforms the same splats with the same Jacobians; the table
counts needles (all, and among splats that were round, anisotropy < 2, in the input), splats
``rotation`` refused (det J <= 0, folded) and the largest anisotropy growth.

``--images DIR`` also writes, for the guitar's 45-degree bend with the drag, the before/after of
every mode side by side (``covariance_modes.png``) and the ``jacobian`` needles in red
(``needles_jacobian.png``), small PNGs for the README.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from data_tools.synth import bumpy_bar  # noqa: E402
from splatdeform import deform as df  # noqa: E402
from splatdeform.deform.gaussians import COVARIANCE_MODES  # noqa: E402
from splatdeform.edit import plain  # noqa: E402
from splatdeform.edit.config import parse_edit  # noqa: E402
from splatdeform.edit.run import precompute  # noqa: E402
from splatdeform.io import load  # noqa: E402
from splatdeform.model import Gaussians, PointModel  # noqa: E402

SHARED = ROOT.parent / "shared" / "data" / "splats"
GROWTH = 4.0
ROUND = 2.0


def round_bar(n: int = 20000, seed: int = 3) -> PointModel:
    """The bumpy bar with round splats (scale jitter 5 %): any needle is the edit's doing."""
    rng = np.random.default_rng(seed)
    bar = bumpy_bar(n, seed=seed)
    q = rng.normal(size=(n, 4))
    g = Gaussians(scale_log=(np.log(0.02) + rng.uniform(-0.05, 0.05, (n, 3))).astype(np.float32),
                  rotation=(q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                  opacity=np.full(n, 3.0, np.float32),
                  sh_dc=rng.normal(0, 0.3, (n, 3)).astype(np.float32))
    return PointModel(positions=bar.positions, gaussians=g, kind="gaussians")


def scene(name: str) -> PointModel:
    if name == "bar":
        return round_bar()
    return load(SHARED / {"guitar": "guitar_3dgs_sh0.ply", "tile": "tile_3dgs_sh3.ply"}[name])


def edit_config(model: PointModel, degrees: float, drag: float) -> dict:
    """Fixed / handle by 40 % slabs along the longest axis a; the handle turns by ``degrees``
    about the third axis c (pivot at the handle's inner face) and moves ``drag`` x size along
    the second axis b (relative units)."""
    lo, hi = model.bbox()
    a, b, c = (int(i) for i in np.argsort(hi - lo)[::-1])
    fmin, fmax, hmin, hmax = np.zeros(3), np.ones(3), np.zeros(3), np.ones(3)
    fmax[a], hmin[a] = 0.4, 0.6
    pivot, axis, move = np.full(3, 0.5), np.zeros(3), np.zeros(3)
    pivot[a], axis[c], move[b] = 0.6, 1.0, drag
    return {
        "input": "x.ply", "output": "y.ply",
        "regions": {"units": "relative", "fixed": [{"box": {"min": fmin.tolist(),
                                                            "max": fmax.tolist()}}],
                    "handle": [{"box": {"min": hmin.tolist(), "max": hmax.tolist()}}]},
        "handle": {"transform": {"pivot": pivot.tolist(),
                                 "rotate": {"axis": axis.tolist(), "degrees": degrees},
                                 "translate": move.tolist()}},
        "boundary": {"continuity": 1, "neighbors": 10},
        "fit": {"tolerance": 2e-3, "max_centers": 1500},
        "backend": "auto",
    }


EDITS = {"bend 45": (45.0, 0.0), "bend 90": (90.0, 0.0), "drag 30%": (0.0, 0.3),
         "bend 45 + drag 30%": (45.0, 0.3)}


def anisotropy(scale_log: np.ndarray) -> np.ndarray:
    return np.exp(np.ptp(np.asarray(scale_log, np.float64), axis=1))


def measure(name: str, images: Path | None) -> list[dict]:
    model = scene(name)
    cfgs = {e: parse_edit(edit_config(model, *v), "bench") for e, v in EDITS.items()}
    t0 = time.perf_counter()
    deformation = precompute(next(iter(cfgs.values())), model, ROOT)
    fit_s = time.perf_counter() - t0
    ratio_in = anisotropy(model.gaussians.scale_log)
    was_round = ratio_in < ROUND
    rows = []
    for edit, cfg in cfgs.items():
        delta_c, matrix = plain.control_displacement(cfg, model, deformation)
        for mode in COVARIANCE_MODES:
            stats: dict = {}
            t0 = time.perf_counter()
            out = df.apply(deformation, model, delta_c, moving_matrix=matrix, covariance=mode,
                           stats=stats)
            growth = anisotropy(out.gaussians.scale_log) / ratio_in
            needle = growth > GROWTH
            rows.append({"scene": name, "splats": model.n_points, "edit": edit, "mode": mode,
                         "needles": int(needle.sum()),
                         "needles_round": int((needle & was_round).sum()),
                         "refused": int(stats.get("refused_splats", 0)),
                         "max_growth": float(growth.max()),
                         "apply_s": time.perf_counter() - t0, "fit_s": fit_s})
            if images is not None and name == "guitar" and edit == "bend 45 + drag 30%" \
                    and mode == "jacobian":
                write_needles(out, needle, images / "needles_jacobian.png")
        if images is not None and name == "guitar" and edit == "bend 45 + drag 30%":
            write_modes(model, deformation, delta_c, images / "covariance_modes.png")
    return rows


def write_needles(deformed: PointModel, needle: np.ndarray, path: Path) -> None:
    from splatdeform.render import View, render_comparison, save_png

    shown = copy.copy(deformed)
    colors = np.full((deformed.n_points, 3), 200, np.uint8)
    colors[needle] = (220, 30, 30)
    shown.colors = colors
    save_png(render_comparison(shown, None, None, View(size=(360, 300)), labels=(
        f"jacobian: {int(needle.sum()):,} needles (red, anisotropy grew > 4x)",)), path)


def write_modes(model: PointModel, deformation, delta_c: np.ndarray, path: Path) -> None:
    from splatdeform.io.image import save_png
    from splatdeform.render.camera import View
    from splatdeform.render.compare import side_by_side
    from splatdeform.render.renderer import deformation_session

    values, gradients = df.full_basis(deformation)
    images, labels = [], []
    for mode in COVARIANCE_MODES:
        with deformation_session(model, values, gradients, delta_c, View(size=(300, 300)),
                                 covariance=mode) as (renderer, gpu, camera):
            if not images:
                images.append(renderer.draw(gpu, camera, None))
                labels.append("before")
            images.append(renderer.draw(gpu, camera, delta_c))
            labels.append(mode)
    save_png(side_by_side(images, labels), path)


def subdivided(model: PointModel) -> tuple[PointModel, np.ndarray]:
    """Every splat as 8 children at (+-0.6, +-0.6, +-0.6) sigma, sigma 0.8x; (8N,) parents."""
    from splatdeform.deform.split import take
    from splatdeform.geometry import quaternion_to_matrix

    n = model.n_points
    parent = np.repeat(np.arange(n), 8)
    out = take(model, parent)
    corners = np.array(np.meshgrid(*[[-0.6, 0.6]] * 3, indexing="ij")).reshape(3, -1).T
    g = model.gaussians
    local = corners[None] * np.exp(g.scale_log.astype(np.float64))[:, None, :]
    rot = quaternion_to_matrix(g.rotation)
    out.positions = (model.positions[:, None, :] + np.einsum("pij,pnj->pni", rot, local)
                     ).reshape(-1, 3)
    out.gaussians.scale_log = (out.gaussians.scale_log + np.float32(np.log(0.8)))
    return out, parent


def rule_children(model: PointModel, which: np.ndarray, m: int = 2
                  ) -> tuple[PointModel, np.ndarray]:
    """The splats where ``which`` (N,) bool as m x m x m children by the project's own split
    rule (``splatdeform.deform.split.children``: moment-matched, opacity keeping the rest look),
    the others whole; (M,) parent rows."""
    from splatdeform.deform.split import children, take

    counts = np.ones((model.n_points, 3), np.int64)
    counts[which] = m
    kids = children(model, np.arange(model.n_points), counts)
    out = take(model, kids.parent)
    out.positions = kids.centers
    out.gaussians.scale_log = kids.scale_log
    if kids.opacity is not None:
        out.gaussians.opacity = kids.opacity
    return out, kids.parent


def reference(model: PointModel, deformation, delta_c, matrix, subdivide=subdivided
              ) -> tuple[PointModel, PointModel]:
    """(rest, deformed) subdivided reference (see the module docstring); ``subdivide(model)``
    -> (rest children, (M,) parent rows) makes the children."""
    from splatdeform.deform import arrays as ap
    from splatdeform.deform.gaussians import deform_gaussians
    from splatdeform.deform.handle import apply_affine
    from splatdeform.deform.split import basis_field

    rest, parent = subdivide(model)
    out = rest.copy()
    jac = np.broadcast_to(np.eye(3), (rest.n_points, 3, 3)).copy()
    label = np.zeros(model.n_points, np.int8)
    label[deformation.free_idx], label[deformation.moving_idx] = 1, 2
    lab = label[parent]
    free, mov = np.flatnonzero(lab == 1), np.flatnonzero(lab == 2)
    field = basis_field(deformation.fit, delta_c)
    out.positions[free], jac[free] = field(rest.positions[free], True)
    out.positions[mov] = apply_affine(matrix, rest.positions[mov])
    row = np.full(model.n_points, -1)
    row[deformation.moving_idx] = np.arange(deformation.moving_idx.size)
    jac[mov] = ap.jacobians(np.ascontiguousarray(deformation.moving_gradients[row[parent[mov]]]),
                            np.asarray(delta_c, np.float64))
    g, gi = out.gaussians, rest.gaussians
    new = deform_gaussians(gi.scale_log, gi.rotation, gi.sh_rest, jac, "jacobian")
    g.scale_log, g.rotation = new.scale_log, new.rotation
    if new.sh_rest is not None:
        g.sh_rest = new.sh_rest
    return rest, out


def psnr(a: np.ndarray, b: np.ndarray, background: np.ndarray) -> tuple[float, float]:
    """Whole-image and masked PSNR (dB) of uint8 images (H, W, 3)."""
    d = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    mask = (a != background).any(axis=2) | (b != background).any(axis=2)

    def db(mse: float) -> float:
        return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)
    return db(d.mean()), db(d[mask].mean() if mask.any() else 0.0)


def measure_psnr(name: str, degrees: float, images: Path | None) -> list[str]:
    from splatdeform.render import View, render_image

    model = _psnr_scene(name)
    cfg = parse_edit(edit_config(model, degrees, 0.0), "bench")
    deformation = precompute(cfg, model, ROOT)
    delta_c, matrix = plain.control_displacement(cfg, model, deformation)
    results, lines = {}, []
    for mode, split in (("limited", "auto"), ("limited", "off"), ("jacobian", "off"),
                        ("jacobian", "auto")):
        stats: dict = {}
        t0 = time.perf_counter()
        results[(mode, split)] = df.apply(deformation, model, delta_c, moving_matrix=matrix,
                                          covariance=mode, stats=stats, split=split)
        moved = model.n_points - int(np.count_nonzero(deformation.fixed))
        lines.append(f"{name} {degrees:g} deg {mode}/{split}: {results[(mode, split)].n_points:,} "
                     f"splats, split {stats.get('split_splats', 0):,} -> "
                     f"{stats.get('split_children', 0):,} children, capped "
                     f"{stats.get('split_capped', 0):,}, growth "
                     f"{(results[(mode, split)].n_points - model.n_points) / moved:.1%} of "
                     f"{moved:,} moved, apply {time.perf_counter() - t0:.2f} s")
    rest, ref = reference(model, deformation, delta_c, matrix)
    default = results[("limited", "auto")]
    panels = []
    for azimuth in (0.0, 90.0):
        cam = View(size=(800, 800), azimuth=azimuth, elevation=0.0).framed(
            [default.positions], [default], 1.0)
        view = View(size=(800, 800), camera=cam)
        ref_img = render_image(ref, view)
        bg = ref_img[0, 0]  # the background colour (the corner is empty)
        floor = psnr(render_image(rest, view), render_image(model, view), bg)
        lines.append(f"  azimuth {azimuth:g}: floor {floor[0]:.2f} dB (masked {floor[1]:.2f})")
        for key, out in results.items():
            img = render_image(out, view)
            p = psnr(img, ref_img, bg)
            lines.append(f"    {key[0]:<9}split {key[1]:<5} {p[0]:.2f} dB (masked {p[1]:.2f}); "
                         f"below floor {floor[0] - p[0]:.2f} dB")
            if azimuth == 0.0 and key in (("limited", "off"), ("limited", "auto")):
                panels.append((img, f"limited, split {key[1]}"))
        if azimuth == 0.0:
            panels.append((ref_img, "reference (8x subdivided, jacobian)"))
    if images is not None:
        from splatdeform.io.image import save_png
        from splatdeform.render.compare import side_by_side

        small = [(im[::4, ::4], label) for im, label in panels]
        save_png(side_by_side([p[0] for p in small], [p[1] for p in small]),
                 images / f"split_{name}_{degrees:g}.png")
    return lines


def diagnose(name: str, degrees: float) -> list[str]:
    """Where the gap to the floor comes from (``--diagnose``): the same PSNR against the issue's
    reference for results that split more than any rule would, and against a finer set that
    keeps the rest look."""
    from splatdeform.render import View, render_image

    model = _psnr_scene(name)
    cfg = parse_edit(edit_config(model, degrees, 0.0), "bench")
    deformation = precompute(cfg, model, ROOT)
    delta_c, matrix = plain.control_displacement(cfg, model, deformation)
    free = np.zeros(model.n_points, bool)
    free[deformation.free_idx] = True
    ours = {f"{mode} split {split}": df.apply(deformation, model, delta_c, moving_matrix=matrix,
                                              covariance=mode, split=split)
            for mode in ("limited", "jacobian") for split in ("off", "auto")}

    def bent(which: np.ndarray) -> tuple[PointModel, PointModel]:
        return reference(model, deformation, delta_c, matrix,
                         subdivide=lambda m: rule_children(m, which))

    issue_ref = reference(model, deformation, delta_c, matrix)
    finer = bent(free)
    extra = {"every free splat split 2x2x2 (the rule's children)": finer[1],
             "only unmoved splats split 2x2x2 (no deformation change)": bent(~free)[1]}
    lines = []
    for azimuth in (0.0, 90.0):
        cam = View(size=(800, 800), azimuth=azimuth, elevation=0.0).framed(
            [ours["limited split auto"].positions], [ours["limited split auto"]], 1.0)
        view = View(size=(800, 800), camera=cam)
        plain_img = render_image(model, view)
        for ref_name, (rest, ref), cands in (
                ("the issue's reference", issue_ref, {**ours, **extra}),
                ("a finer set keeping the rest look (free splats 2x2x2)", finer, ours)):
            ref_img = render_image(ref, view)
            bg = ref_img[0, 0]
            floor = psnr(render_image(rest, view), plain_img, bg)[0]
            lines.append(f"{name} {degrees:g} deg, azimuth {azimuth:g}, against {ref_name}: "
                         f"floor {floor:.2f} dB")
            for label, out in cands.items():
                p = psnr(render_image(out, view), ref_img, bg)[0]
                lines.append(f"    {label:<58}{p:6.2f} dB, {floor - p:5.2f} below the floor")
    return lines


def _psnr_scene(name: str) -> PointModel:
    """``gbar``: the generated Gaussian bar, 20,000 splats; ``gbar150``: 150,000 of them."""
    if name in ("gbar", "gbar150"):
        from data_tools.synth import gaussian_bar
        return gaussian_bar(20000 if name == "gbar" else 150000)
    return scene(name)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="guitar,tile,bar")
    ap.add_argument("--images", type=Path, help="write the README images into this folder")
    ap.add_argument("--psnr", help="scene:degrees,... (guitar, tile, bar, gbar, gbar150): "
                    "issue 37")
    ap.add_argument("--diagnose", help="scene:degrees,...: where the gap to the floor comes from")
    args = ap.parse_args(argv)
    if args.images is not None:
        args.images.mkdir(parents=True, exist_ok=True)
    if args.psnr or args.diagnose:
        for item in (args.psnr or args.diagnose).split(","):
            name, degrees = item.split(":")
            lines = (measure_psnr(name, float(degrees), args.images) if args.psnr
                     else diagnose(name, float(degrees)))
            for line in lines:
                print(line, flush=True)
        return
    print(f"{'scene':<8}{'splats':>8}  {'edit':<20}{'mode':<10}{'needles':>9}{'of round':>10}"
          f"{'refused':>9}{'max growth':>12}{'apply s':>9}")
    for name in args.scenes.split(","):
        for r in measure(name, args.images):
            print(f"{r['scene']:<8}{r['splats']:>8,}  {r['edit']:<20}{r['mode']:<10}"
                  f"{r['needles']:>9,}{r['needles_round']:>10,}{r['refused']:>9,}"
                  f"{r['max_growth']:>12.3g}{r['apply_s']:>9.2f}", flush=True)


if __name__ == "__main__":
    main()
