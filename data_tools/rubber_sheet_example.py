"""The rubber-sheeting example (``points:``, issue 36) from generated data.

A 400 m x 2 km terrain strip "scanned" on a long drive whose trajectory drifted: the scan is the
true terrain under a smooth known warp (a drift growing along the strip to ~7 m plus two broad
bumps of 2-3 m). Twelve surveyed control points give pairs (where each lies in the drifted scan
-> its surveyed position); ``splatdeform deform configs/rubber_sheet.yaml`` warps the scan back
through them.

``python -m data_tools.rubber_sheet_example OUT_DIR`` writes ``OUT_DIR/drifted_scan.ply`` and
``OUT_DIR/gcp.csv`` (what ``configs/rubber_sheet.yaml`` reads from ``demo_out/rubber_sheet``);
``--image PNG`` also runs the edit and draws before / after coloured by the distance to the
true terrain, with the pairs as arrows (the README's ``docs/images/rubber_sheet.png``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from splatdeform.examples.terrain import N_PAIRS, N_POINTS, control_indices, drift, pairs_csv, truth
from splatdeform.model import PointModel

__all__ = ["N_PAIRS", "N_POINTS", "control_indices", "drift", "truth", "write_inputs"]
MAX_ERROR = 8.0   # metres: the top of the colour ramp


def write_inputs(out_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """drifted_scan.ply and gcp.csv in ``out_dir`` (:mod:`splatdeform.examples.terrain`, as
    ``splatdeform example rubber_sheet`` writes them); returns (truth, drifted) (N, 3)."""
    from splatdeform.io import save

    out_dir.mkdir(parents=True, exist_ok=True)
    true = truth()
    scan = drift(true)
    save(PointModel(positions=scan), out_dir / "drifted_scan.ply")
    (out_dir / "gcp.csv").write_text(pairs_csv(true, scan))
    return true, scan


def error_colors(p: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(N, 3) uint8: distance to the truth on a blue -> yellow -> red ramp (0..MAX_ERROR m)."""
    t = np.clip(np.linalg.norm(p - true, axis=1) / MAX_ERROR, 0, 1)[:, None]
    blue, yellow, red = (np.array(c, float) for c in ((40, 80, 200), (240, 210, 40),
                                                      (200, 30, 30)))
    rgb = np.where(t < 0.5, blue + (yellow - blue) * (2 * t), yellow + (red - yellow) *
                   (2 * t - 1))
    return rgb.astype(np.uint8)


def make_image(config: Path, image: Path) -> None:
    """Run the edit (the config's in-memory path) and draw before / after with the pairs."""
    from PIL import Image

    from splatdeform.edit.config import load_edit
    from splatdeform.edit.metaphors.points import pairs_of
    from splatdeform.edit.run import run_edit
    from splatdeform.render import View, render_comparison
    from splatdeform.render.pairs import pair_overlays

    true = truth()
    cfg = load_edit(config)
    base = config.resolve().parent
    result = run_edit(cfg, base, save_output=False)
    before, after = result.model, result.deformed
    err_b = np.linalg.norm(before.positions - true, axis=1)
    err_a = np.linalg.norm(after.positions - true, axis=1)
    pairs, _ = pairs_of(cfg, before, base)
    view = View(size=(440, 330), azimuth=-35, elevation=50, up="+z")
    overlays, legend = pair_overlays(pairs.sources, pairs.targets, view,
                                [before.positions, after.positions], [before])
    shown_b = PointModel(positions=before.positions, colors=error_colors(before.positions, true))
    shown_a = PointModel(positions=after.positions, colors=error_colors(after.positions, true))
    rgb = render_comparison(shown_b, shown_a, None, view, overlays=overlays, labels=(
        f"before: drifted scan, error RMS {np.sqrt(np.mean(err_b ** 2)):.2f} m"
        + (f" (arrows x{legend.split(' drawn x')[1].split(' ')[0]})" if " drawn x" in legend
           else ""),
        f"after: {pairs.n} pairs, error RMS {np.sqrt(np.mean(err_a ** 2)):.2f} m"))
    pic = Image.fromarray(rgb).quantize(64, method=Image.Quantize.MEDIANCUT)
    image.parent.mkdir(parents=True, exist_ok=True)
    pic.save(image, optimize=True)
    print(f"wrote {image} ({image.stat().st_size / 1024:.0f} KB); error RMS before "
          f"{np.sqrt(np.mean(err_b ** 2)):.3f} m, after {np.sqrt(np.mean(err_a ** 2)):.3f} m, "
          f"max after {err_a.max():.3f} m (colour: distance to the truth, 0 blue .. "
          f"{MAX_ERROR:g} m red)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--image", type=Path, help="also run the edit and draw before/after")
    ap.add_argument("--config", type=Path, default=Path("configs/rubber_sheet.yaml"))
    args = ap.parse_args()
    write_inputs(args.out_dir)
    print(f"wrote {args.out_dir / 'drifted_scan.ply'} and {args.out_dir / 'gcp.csv'}")
    if args.image:
        make_image(args.config, args.image)


if __name__ == "__main__":
    main()
