"""Editor latency per pose change.

Default (the page, ``splatdeform edit``): the editor's WebGL2 page in headless chromium with
software WebGL (SwiftShader). For a 40k-point scan (../shared/data armadillo, else a generated
bar) and 152k generated Gaussians: fit once, then per pose the bytes sent (the ``pose`` message)
and pose -> drawn frame timed inside the page (input time to the animation frame after the
draw, with gl.finish), plus the once-per-fit basis upload. Targets: <= 1 KB per pose,
<= 100 ms (40k points), <= 1 s (152k Gaussians) in software WebGL.
``--busy 2`` repeats beside two CPU-busy processes. (The viser viewer and its ``--viser``
benchmark were retired: the page is the one editor.) The chromium driver is the tests' helper
``tests/browser.py``.

    python benchmarks/bench_editor.py [--poses 10] [--busy 2]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # browser.py: the tests' chromium driver

from data_tools.synth import bumpy_bar, gaussian_bar  # noqa: E402
from splatdeform.deform.handle import compose_transform  # noqa: E402
from splatdeform.edit.selectors import Box  # noqa: E402

SCAN = ROOT.parent / "shared" / "data" / "scans" / "armadillo_oriented.ply"


def _spin(stop) -> None:
    while not stop.is_set():
        sum(i * i for i in range(10000))


def page_case(label: str, path: Path, poses: int, covariance: str = "limited"
              ) -> dict[str, float]:
    """Fit end boxes on ``path`` in the page's session, then time poses in chromium
    (Gaussians drawn with ``gaussians.covariance`` = ``covariance``)."""
    from browser import Chromium

    from splatdeform.editor.page_server import make_server

    srv = make_server(path, port=0)
    ed = srv.session.ed
    ed.settings.gaussians.covariance = covariance
    srv.scene["covariance"] = covariance
    lo, hi = ed.model.bbox()
    axis = int(np.argmax(hi - lo))
    ext = hi - lo
    for role, at in (("fixed", 0.1), ("handle", 0.9)):
        c = (lo + hi) / 2
        c[axis] = lo[axis] + at * ext[axis]
        size = ext * 1.2
        size[axis] = 0.2 * ext[axis]
        ed.add_selector(role, Box(tuple(c - size / 2), tuple(c + size / 2)))
    ed.settings.fit.tolerance = 1e-3
    t0 = time.perf_counter()
    srv.session.act({"op": "fit"})
    fit_s = time.perf_counter() - t0
    basis_bytes = srv.session.basis().nbytes
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    try:
        with Chromium(size=(1280, 800), timeout=300) as tab:
            t0 = time.perf_counter()
            tab.open(srv.url())
            tab.wait("window.sdReady === true || !!window.sdError", 600)
            load_s = time.perf_counter() - t0
            err = tab.eval("window.sdError || ''")
            if err:
                raise RuntimeError(err)
            pivot = ed.deformation.handle_groups()[0].frame.control_points[0] - ed.origin
            times, draws = [], []
            tab.eval("sdBenchPose([[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]])")  # warm-up
            for i in range(poses):
                m = compose_transform(pivot=pivot, axis=(0, 0, 1), degrees=2.0 * (i + 1),
                                      translate=(0, 0.01 * (i + 1) * ext.max(), 0))
                times.append(tab.eval(f"sdBenchPose({json.dumps(m.tolist())})"))
                draws.append(tab.eval("sdStats.lastDrawMs"))
            # what one drag step sends: the page's own pose message
            tab.eval(f"sdAct({{op: 'pose', handle: 0, matrix: {json.dumps(m.tolist())}}})")
            pose_bytes = tab.eval("sdStats.poseBytes")
            sort_ms = tab.eval("sdStats.sortMs")
    finally:
        srv.shutdown()
        srv.server_close()
    return {"label": label, "n": ed.model.n_points, "fit_s": fit_s, "load_s": load_s,
            "basis_mb": basis_bytes / 2**20, "pose_bytes": pose_bytes,
            "median_ms": float(np.median(times)), "max_ms": float(np.max(times)),
            "draw_ms": float(np.median(draws)), "sort_ms": sort_ms}


def page_main(poses: int, busy: int) -> None:
    from splatdeform.io import save

    with tempfile.TemporaryDirectory() as tmp:
        if SCAN.is_file():
            scan, scan_label = SCAN, "armadillo scan (points, normals)"
        else:
            scan, scan_label = Path(tmp) / "bar40k.ply", "generated bar (surfels)"
            save(bumpy_bar(40_000), scan)
        splats = Path(tmp) / "gauss152k.ply"
        save(gaussian_bar(152_000), splats)
        for load in ([0, busy] if busy else [0]):
            stop = multiprocessing.Event()
            procs = [multiprocessing.Process(target=_spin, args=(stop,)) for _ in range(load)]
            for p in procs:
                p.start()
            try:
                rows = [page_case(scan_label, scan, poses)]
                rows += [page_case(f"generated 3DGS (SH 0), covariance {mode}", splats, poses,
                                   mode) for mode in ("limited", "jacobian")]
            finally:
                stop.set()
                for p in procs:
                    p.join()
            print(f"\n{'idle' if not load else f'beside {load} CPU-busy processes'}: headless "
                  "chromium, SwiftShader WebGL2")
            print("| model | N | fit | page load (model + basis) | basis upload | bytes per pose"
                  " | pose -> frame median / max | draw | sort |\n|---|---|---|---|---|---|---|"
                  "---|---|")
            for r in rows:
                print(f"| {r['label']} | {r['n']:,} | {r['fit_s']:.1f} s | {r['load_s']:.1f} s | "
                      f"{r['basis_mb']:.1f} MiB | {r['pose_bytes']} B | {r['median_ms']:.0f} / "
                      f"{r['max_ms']:.0f} ms | {r['draw_ms']:.0f} ms | {r['sort_ms']:.0f} ms |")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=10)
    ap.add_argument("--busy", type=int, default=0, help="also run beside N CPU-busy processes")
    args = ap.parse_args(argv)
    page_main(args.poses, args.busy)


if __name__ == "__main__":
    main()
