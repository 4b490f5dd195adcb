"""The control-points guide's commands make the picture the guide shows (issue 48 item 4): its
bash lines run in order in a scratch folder (configs/rubber_sheet.yaml copied in), the picture
they draw is coloured (many hues: the error ramp, and the magenta pair arrows), not two plain
grey strips, and the error figures they print are the guide's; deform's own before/after is
coloured too (render.color: elevation). No pixel comparison with the committed PNG."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "guides" / "control-points.md"


def _hues(path: Path) -> tuple[int, float]:
    """(distinct hue bins of 36 among saturated pixels, fraction of magenta-ish pixels)."""
    hsv = np.asarray(Image.open(path).convert("RGB").convert("HSV")).reshape(-1, 3)
    vivid = hsv[(hsv[:, 1] > 80) & (hsv[:, 2] > 60)]
    bins = np.unique(vivid[:, 0].astype(int) * 36 // 256).size
    magenta = np.mean((hsv[:, 1] > 120) & (np.abs(hsv[:, 0].astype(int) - 213) < 14))
    return bins, float(magenta)


def test_the_guides_commands_draw_its_coloured_picture(tmp_path):
    text = GUIDE.read_text()
    section = text.split("### Example: rubber-sheeting", 1)[1].split("\n## ", 1)[0]
    image = re.search(r"\]\(\.\./images/(\w+\.png)\)", section).group(1)
    assert (ROOT / "docs" / "images" / image).is_file()
    blocks = re.findall(r"```bash\n(.*?)```", section, flags=re.S)
    lines = [ln.split("#", 1)[0].strip() for b in blocks for ln in b.splitlines()]
    lines = [ln for ln in lines if ln]
    assert any(f"--image {image}" in ln for ln in lines), "no command draws the guide's image"
    (tmp_path / "configs").mkdir()
    shutil.copy(ROOT / "configs" / "rubber_sheet.yaml", tmp_path / "configs")
    env = {**os.environ, "PYTHONPATH": str(ROOT),
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    printed = ""
    for line in lines:
        line = re.sub(r"^python ", f"{sys.executable} ", line)
        run = subprocess.run(line, shell=True, cwd=tmp_path, env=env, capture_output=True,
                             text=True, timeout=300)
        assert run.returncode == 0, f"{line}: {run.stdout}{run.stderr}"
        printed += run.stdout
    bins, magenta = _hues(tmp_path / image)
    assert bins >= 4 and magenta > 1e-4, (bins, magenta)   # the ramp and the arrows
    # the figures the guide quotes are the ones the command prints
    before, after = re.search(r"falls from ([\d.]+) m RMS\s+before to ([\d.]+) m after",
                              section).groups()
    got = re.search(r"error RMS before ([\d.]+) m, after ([\d.]+) m", printed).groups()
    assert [f"{float(v):.2f}" for v in got] == [before, after]
    warped = tmp_path / "demo_out" / "rubber_sheet" / "warped.png"
    assert _hues(warped)[0] >= 3                           # not two plain grey strips
    assert (tmp_path / "pairs.png").is_file() and (tmp_path / "residuals.csv").is_file()


def test_the_packaged_example_is_the_guides_data(tmp_path):
    """``splatdeform example rubber_sheet`` (what a pip user has) writes the clone's example
    scan and pairs byte for byte, and its config runs (issue 48: the quick start outside the
    clone)."""
    from data_tools.rubber_sheet_example import write_inputs
    from splatdeform.examples import write_example

    write_inputs(tmp_path / "clone")
    written = write_example("rubber_sheet", tmp_path / "pip")
    assert [p.relative_to(tmp_path / "pip").as_posix() for p in written] == [
        "scans/drifted_scan.ply", "scans/gcp.csv", "rubber_sheet.yaml"]
    for name in ("drifted_scan.ply", "gcp.csv"):
        assert (tmp_path / "pip" / "scans" / name).read_bytes() == \
            (tmp_path / "clone" / name).read_bytes()
    run = subprocess.run([sys.executable, "-m", "splatdeform.cli", "deform",
                          "rubber_sheet.yaml", "--residuals", "residuals.csv"],
                         cwd=tmp_path / "pip", capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "pairs 12 (smoothing 0)" in run.stdout
    assert (tmp_path / "pip" / "out" / "warped.ply").is_file()
    assert _hues(tmp_path / "pip" / "out" / "warped.png")[0] >= 3
