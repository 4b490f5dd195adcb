"""Needles of deformed 3D Gaussian splats per ``gaussians.covariance`` mode (issue 22), and
the PSNR of every mode against a reference that keeps the rest look (issue 46, ``--psnr``).

    python benchmarks/bench_needles.py [--scenes guitar,tile,bar] [--images docs/images]
    python benchmarks/bench_needles.py --psnr guitar:75,surf150:60,gbar:90 [--images docs/images]

``--psnr`` (issue 46): one fit per scene (fixed: the first 40 % along the longest axis; handle:
the last 40 %, turned by the given degrees), the basis deferred as ``deform`` makes it, and
every mode (covariance limited / jacobian / rotation x split auto / off): apply time (best of
three for ``limited``), splits, and needles: output splats of free parents whose longest axis
exceeds 2.2 x the parent's longest x det(J)^(1/3). The reference replaces only the free-region
splats: each principal axis k with sigma_k >= 0.3 sigma_max gets 5 children at 0, +-0.88,
+-1.76 sigma_k with weights 0.391, 0.245, 0.060 (products across the split axes), child sigma
0.5 sigma_k; each child moves by the float64 field at its own centre with its own J
(``jacobian``); fixed rows stay, handle rows move as ``deform`` moves them. Opacity per view
("screen mass", :func:`screen_mass_opacity`). Rendered at 800 x 800 from a camera framing the
default result and the rest scene, front (azimuth 0) and side (90): PSNR over the whole image
and over the moved region (pixels where the reference or unsplit ``jacobian`` differ from the
rest render). The rest floor is the reference at rest (J = I) against the original.
``surf150``: :func:`surface_scene` (150,000 surface splats of >= 3 px); ``gbar``: the 20,000
sub-pixel Gaussian bar, needles and times only.

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


# the issue-46 reference: 5 children per split axis (offsets in sigma, weights), child sigma
REF_OFFSETS = np.array([0.0, -0.88, 0.88, -1.76, 1.76])
REF_WEIGHTS = np.array([0.391, 0.245, 0.245, 0.060, 0.060])
REF_CHILD_SIGMA = 0.5
REF_SPLIT_MIN = 0.3  # axes with sigma >= this x sigma_max are split
LOW_PASS = 0.3  # px^2, the rasteriser's
NEEDLE = 2.2  # output longest axis > this x parent's longest x det(J)^(1/3)


def surface_scene(n: int = 150000, seed: int = 4) -> PointModel:
    """The bumpy bar (4 x 1 x 1) as ``n`` flat surface splats that cover >= 3 px each at
    800 x 800: tangent sigmas 0.012-0.03 (the bar spans ~700 px), normal sigma 0.002, mostly
    opaque, coloured by a pattern of stripes and rings (so a misplaced splat shows)."""
    from splatdeform.geometry import matrix_to_quaternion

    rng = np.random.default_rng(seed)
    bar = bumpy_bar(n, seed=seed)
    nrm = bar.normals
    helper = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(nrm, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(nrm, t1)
    ang = rng.uniform(0, np.pi, n)[:, None]
    a, b = np.cos(ang) * t1 + np.sin(ang) * t2, -np.sin(ang) * t1 + np.cos(ang) * t2
    rot = np.stack([a, b, nrm], axis=2)  # columns: the axes
    rot[np.linalg.det(rot) < 0, :, 2] *= -1
    sig = np.stack([rng.uniform(0.012, 0.03, n), rng.uniform(0.012, 0.03, n),
                    np.full(n, 0.002)], axis=1)
    x, th = bar.positions[:, 0], np.arctan2(bar.positions[:, 2], bar.positions[:, 1])
    col = np.stack([np.sin(6 * x), np.cos(5 * th), np.sin(3 * x + 2 * th)], axis=1)
    g = Gaussians(scale_log=np.log(sig).astype(np.float32),
                  rotation=matrix_to_quaternion(rot).astype(np.float32),
                  opacity=rng.normal(2.0, 0.5, n).astype(np.float32),
                  sh_dc=(1.2 * col).astype(np.float32))
    return PointModel(positions=bar.positions, gaussians=g, kind="gaussians")


def reference_children(model: PointModel, rows: np.ndarray) -> dict:
    """The issue's children of splats ``rows`` (P,): per child its parent row, rest centre,
    log-scale, weight w_j (products across the split axes) and rest covariance (C, 3, 3)."""
    from splatdeform.geometry import quaternion_to_matrix

    g = model.gaussians
    sigma = np.exp(g.scale_log[rows].astype(np.float64))
    rot = quaternion_to_matrix(g.rotation[rows])
    split = sigma >= REF_SPLIT_MIN * sigma.max(axis=1, keepdims=True)
    parts = []
    for pattern in np.unique(split, axis=0):
        sel = np.flatnonzero((split == pattern).all(axis=1))
        offs = [REF_OFFSETS if k else np.zeros(1) for k in pattern]
        wts = [REF_WEIGHTS if k else np.ones(1) for k in pattern]
        grid = np.stack([v.ravel() for v in np.meshgrid(*offs, indexing="ij")], axis=1)
        w = np.prod([v.ravel() for v in np.meshgrid(*wts, indexing="ij")], axis=0)
        n = grid.shape[0]
        local = grid[None] * sigma[sel, None, :]
        centers = model.positions[rows[sel], None, :] + np.einsum("pij,pnj->pni", rot[sel], local)
        child_sigma = sigma[sel] * np.where(pattern, REF_CHILD_SIGMA, 1.0)
        parts.append((np.repeat(rows[sel], n), np.repeat(sel, n), centers.reshape(-1, 3),
                      np.repeat(np.log(child_sigma), n, axis=0), np.tile(w, sel.size)))
    cat = [np.concatenate([p[i] for p in parts]) for i in range(5)]
    return {"parent": cat[0], "slot": cat[1], "centers": cat[2], "scale_log": cat[3],
            "weight": cat[4]}


def _cov(scale_log: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    from splatdeform.geometry import quaternion_to_matrix

    r = quaternion_to_matrix(rotation)
    return np.einsum("mij,mj,mkj->mik", r, np.exp(2 * scale_log.astype(np.float64)), r)


def _screen(camera, size: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (M, 2) and the projection's Jacobian (M, 2, 3) (world -> px)."""
    import math

    right, up, fwd = camera.basis()
    rel = points - camera.eye()
    xc, yc, z = rel @ right, rel @ up, rel @ fwd
    f = (size / 2) / math.tan(math.radians(camera.fov) / 2)
    z = np.maximum(z, 1e-9)
    uv = np.stack([f * xc / z, f * yc / z], axis=1)
    jp = np.zeros((points.shape[0], 2, 3))
    jp[:, 0] = f / z[:, None] * right - (f * xc / z ** 2)[:, None] * fwd
    jp[:, 1] = f / z[:, None] * up - (f * yc / z ** 2)[:, None] * fwd
    return uv, jp


def screen_mass_opacity(model: PointModel, kids: dict, rows: np.ndarray, mu: np.ndarray,
                        jac: np.ndarray, camera, size: int) -> np.ndarray:
    """Child opacity logits for one view: alpha_j = 1 - exp(-tau_j), tau_j = w_j r_j
    tau(alpha G_j) / G_j (see the issue): r_j = sqrt(det S / det S_j) of the parent's and the
    child's screen covariances (+ the 0.3 px^2 low-pass), both mapped by the parent's J; G_j the
    parent's footprint at the child's centre mapped by the parent's J. ``mu`` (P, 3) and ``jac``
    (P, 3, 3): the parents' deformed centres and Jacobians (rows ``rows``)."""
    g = model.gaussians
    slot = kids["slot"]
    cov_p = _cov(g.scale_log[rows], g.rotation[rows])
    cov_c = _cov(kids["scale_log"], g.rotation[kids["parent"]])
    uv_p, jp = _screen(camera, size, mu)
    mapped_p = np.einsum("pij,pjk,plk->pil", jac, cov_p, jac)
    s_p = np.einsum("pij,pjk,plk->pil", jp, mapped_p, jp) + LOW_PASS * np.eye(2)
    jc = jac[slot]
    s_c = np.einsum("cij,cjk,clk->cil", jp[slot], np.einsum("cij,cjk,clk->cil", jc, cov_c, jc),
                    jp[slot]) + LOW_PASS * np.eye(2)
    r = np.sqrt(np.linalg.det(s_p)[slot] / np.linalg.det(s_c))
    centre = mu[slot] + np.einsum("cij,cj->ci", jc, kids["centers"] - model.positions[
        kids["parent"]])
    d = _screen(camera, size, centre)[0] - uv_p[slot]
    gj = np.exp(-0.5 * np.einsum("ci,cij,cj->c", d, np.linalg.inv(s_p)[slot], d))
    alpha = 1 / (1 + np.exp(-g.opacity[kids["parent"]].astype(np.float64)))
    tau_a = -np.log1p(-np.minimum(0.99, alpha * gj))
    tau = kids["weight"] * r * np.divide(tau_a, gj, out=np.zeros_like(gj), where=gj > 0)
    with np.errstate(divide="ignore"):
        return np.log(np.expm1(tau)).astype(np.float32)


class Reference:
    """The issue-46 reference of one edit: non-free rows as ``deform`` moves them (fixed
    bit-identical, handle rows by the handle's map), free splats as 5-per-split-axis children
    each moved by the float64 field at its own centre with its own J (``jacobian``); opacity per
    view (:func:`screen_mass_opacity`)."""

    def __init__(self, model: PointModel, deformation, delta_c, matrix) -> None:
        from splatdeform.deform.gaussians import deform_gaussians
        from splatdeform.deform.split import basis_field, concat, take

        free = deformation.free_idx
        keep = np.ones(model.n_points, bool)
        keep[free] = False
        whole = df.apply(deformation, model, delta_c, moving_matrix=matrix,
                         covariance="jacobian", split="off")
        self.model, self.free = model, free
        self.kids = reference_children(model, free)
        field = basis_field(deformation.fit, delta_c)
        self.mu, self.jac = field(model.positions[free], True)
        rest = take(model, self.kids["parent"])
        rest.positions = self.kids["centers"]
        rest.gaussians.scale_log = self.kids["scale_log"].astype(np.float32)
        moved = rest.copy()
        moved.positions, jac = field(self.kids["centers"], True)
        gi = rest.gaussians
        new = deform_gaussians(gi.scale_log, gi.rotation, gi.sh_rest, jac, "jacobian")
        moved.gaussians.scale_log, moved.gaussians.rotation = new.scale_log, new.rotation
        if new.sh_rest is not None:
            moved.gaussians.sh_rest = new.sh_rest
        others = np.flatnonzero(keep)
        self.rest = concat(take(model, others), rest)
        self.bent = concat(take(whole, others), moved)
        self.n_others = others.size

    def at(self, camera, size: int, bent: bool) -> PointModel:
        """The rest or bent reference with its opacities for ``camera``."""
        out = (self.bent if bent else self.rest).copy()
        mu = self.mu if bent else self.model.positions[self.free].astype(np.float64)
        jac = self.jac if bent else np.broadcast_to(np.eye(3), (self.free.size, 3, 3))
        out.gaussians.opacity[self.n_others:] = screen_mass_opacity(
            self.model, self.kids, self.free, mu, jac, camera, size)
        return out


def needles(model: PointModel, out: PointModel, deformation, delta_c, stats: dict) -> int:
    """Output splats of free parents whose longest axis exceeds 2.2 x the parent's longest x
    det(J)^(1/3), J the output splat's own (the parent's at its centre, a child's at the
    child's; float64 for whole splats, the apply's own for children)."""
    from splatdeform.deform.split import basis_field

    n = model.n_points
    parent = np.concatenate([np.arange(n), np.asarray(stats.get("parent_rows", []), np.int64)])
    free = np.zeros(n, bool)
    free[deformation.free_idx] = True
    _, jac = basis_field(deformation.fit, delta_c)(model.positions[deformation.free_idx], True)
    cbrt = np.ones(parent.size)
    cbrt[deformation.free_idx] = np.cbrt(np.abs(np.linalg.det(jac)))
    kids = stats.get("child_jacobians")
    if isinstance(kids, tuple):
        kp, kc, kj = kids
        rows = np.empty(kp.size, np.int64)
        rows[kc == 0] = kp[kc == 0]
        rows[kc != 0] = n + np.arange(np.count_nonzero(kc != 0))
        cbrt[rows] = np.cbrt(np.abs(np.linalg.det(kj)))
    longest = np.exp(model.gaussians.scale_log.astype(np.float64).max(axis=1))
    out_longest = np.exp(out.gaussians.scale_log.astype(np.float64).max(axis=1))
    sel = free[parent]
    return int(np.count_nonzero(out_longest[sel] > NEEDLE * longest[parent[sel]] * cbrt[sel]))


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of uint8 images (H, W, 3), over ``mask`` (H, W) when given."""
    d = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    mse = d[mask].mean() if mask is not None else d.mean()
    return float("inf") if mse == 0 else float(10 * np.log10(255.0 ** 2 / mse))


# front / side per scene (azimuth, elevation): the guitar as issue 46 measured it; the bar
# bends about y, so its front looks along y (the bend in profile) and its side along z
VIEWS = {"guitar": [("front", 0.0, 0.0), ("side", 90.0, 0.0)],
         "surf150": [("front", 0.0, 90.0), ("side", 0.0, 0.0)]}
MODES = [(c, s) for s in ("auto", "off") for c in ("limited", "jacobian", "rotation")]


def measure_psnr(name: str, degrees: float, images: Path | None, psnr_views: bool = True,
                 repeats: int = 3) -> list[str]:
    """The issue-46 table for one scene: per mode (covariance x split) the apply time (best of
    ``repeats``, one-shot basis as ``deform``), splits, needles, and (``psnr_views``) PSNR
    against the reference, whole image and moved-region mask, front and side."""
    from splatdeform.render import View, render_image

    model = _psnr_scene(name)
    cfg = parse_edit(edit_config(model, degrees, 0.0), "bench")
    deformation = precompute(cfg, model, ROOT, stored=False)  # as deform: one-shot
    delta_c, matrix = plain.control_displacement(cfg, model, deformation)
    free = deformation.free_idx.size
    lines = [f"{name}: {model.n_points:,} splats, {free:,} free, bent {degrees:g} deg"]
    results = {}
    for mode, split in MODES:
        best, stats = np.inf, {}
        for _ in range(repeats if mode == "limited" else 1):
            stats = {"child_jacobians": None}
            t0 = time.perf_counter()
            out = df.apply(deformation, model, delta_c, moving_matrix=matrix, covariance=mode,
                           stats=stats, split=split)
            best = min(best, time.perf_counter() - t0)
        results[(mode, split)] = out
        nd = needles(model, out, deformation, delta_c, stats)
        lines.append(f"  {mode:<9}split {split:<5} apply {best:6.3f} s  split "
                     f"{stats.get('split_splats', 0):,} -> {stats.get('split_children', 0):,} "
                     f"(capped {stats.get('split_capped', 0):,})  needles {nd:,} "
                     f"({nd / max(free, 1):.2%} of free)")
    if not psnr_views:
        return lines
    t0 = time.perf_counter()
    ref = Reference(model, deformation, delta_c, matrix)
    lines.append(f"  reference: {ref.kids['parent'].size:,} children of {free:,} free splats "
                 f"({time.perf_counter() - t0:.1f} s)")
    panels = []
    for view_name, azimuth, elevation in VIEWS.get(name, VIEWS["guitar"]):
        default = results[("limited", "auto")]
        cam = View(size=(800, 800), azimuth=azimuth, elevation=elevation).framed(
            [default.positions, model.positions], [default], 1.0)
        view = View(size=(800, 800), camera=cam)
        ref_img = render_image(ref.at(cam, 800, True), view)
        rest_img = render_image(model, view)
        floor = psnr(render_image(ref.at(cam, 800, False), view), rest_img)
        # the moved region: pixels where the unsplit jacobian result or the reference differ
        # from the rest image
        plain_img = render_image(results[("jacobian", "off")], view)
        mask = (ref_img != rest_img).any(axis=2) | (plain_img != rest_img).any(axis=2)
        if view_name == "front":
            front_mask = mask
        lines.append(f"  {view_name} (azimuth {azimuth:g}, elevation {elevation:g}): rest floor "
                     f"{floor:.2f} dB "
                     f"(the reference at rest against the original); moved mask "
                     f"{mask.mean():.1%} of the image")
        for key, out in results.items():
            img = plain_img if key == ("jacobian", "off") else render_image(out, view)
            lines.append(f"    {key[0]:<9}split {key[1]:<5} {psnr(img, ref_img):6.2f} dB whole, "
                         f"{psnr(img, ref_img, mask):6.2f} dB moved; "
                         f"{floor - psnr(img, ref_img):5.2f} below the floor")
            if view_name == "front" and key in (("limited", "off"), ("limited", "auto")):
                panels.append((img, f"limited, split {key[1]}"))
        if view_name == "front":
            panels.append((ref_img, "reference (issue 46)"))
    if images is not None:
        from splatdeform.io.image import save_png
        from splatdeform.render.compare import side_by_side

        ys, xs = np.nonzero(front_mask)  # a full-resolution crop of the moved region
        cy, cx = (int(np.median(ys)), int(np.median(xs))) if ys.size else (400, 400)
        y0, x0 = min(max(cy - 150, 0), 500), min(max(cx - 150, 0), 500)
        crops = [(im[y0:y0 + 300, x0:x0 + 300], label) for im, label in panels[:3]]
        save_png(side_by_side([p[0] for p in crops], [p[1] for p in crops]),
                 images / f"split_{name}_{degrees:g}.png")
    return lines


def _psnr_scene(name: str) -> PointModel:
    """``gbar``: the generated Gaussian bar, 20,000 sub-pixel splats (needles only);
    ``surf150``: :func:`surface_scene`, 150,000 splats of >= 3 px."""
    if name == "gbar":
        from data_tools.synth import gaussian_bar
        return gaussian_bar(20000)
    if name == "surf150":
        return surface_scene(150000)
    return scene(name)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="guitar,tile,bar")
    ap.add_argument("--images", type=Path, help="write the README images into this folder")
    ap.add_argument("--psnr", help="scene:degrees,... (guitar, surf150, gbar, tile, bar): the "
                    "issue-46 table (gbar: needles and apply times only, sub-pixel splats)")
    args = ap.parse_args(argv)
    if args.images is not None:
        args.images.mkdir(parents=True, exist_ok=True)
    if args.psnr:
        for item in args.psnr.split(","):
            name, degrees = item.split(":")
            for line in measure_psnr(name, float(degrees), args.images,
                                     psnr_views=name != "gbar"):
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
