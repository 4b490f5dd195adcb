"""The examples' edit configs, as the files ``splatdeform example`` writes (the README's quick
start shows ``BEND`` as it is; tests/test_docs.py checks that they agree)."""

from __future__ import annotations

BEND = """\
input: scans/bar.ply
output: out/bar_bent.ply
regions:
  units: relative                  # coordinates in [0,1]^3 of the bounding box
  fixed:  [{box: {min: [0, 0, 0], max: [0.25, 1, 1]}}]
  handle: [{box: {min: [0.75, 0, 0], max: [1, 1, 1]}}]
handle:
  transform:
    pivot: [0.75, 0.5, 0.5]
    rotate: {axis: [0, 0, 1], degrees: 35}
    translate: [0, 0.1, 0]
"""

CURVE = """\
# A cubic curve along the top of the bar: its two middle control points are raised, both ends
# of the bar stay fixed (model units: the bar runs from x = 0 to 4, radius 0.5).
input: scans/bar.ply
output: out/bar_curve.ply
regions:
  units: model
  fixed:
    - {box: {min: [-1, -1, -1], max: [0.6, 1, 1]}}
    - {box: {min: [3.4, -1, -1], max: [5, 1, 1]}}
curve:
  control_points: [[1.2, 0.5, 0], [1.7, 0.5, 0], [2.3, 0.5, 0], [2.8, 0.5, 0]]
  moved_to:       [[1.2, 0.5, 0], [1.7, 0.85, 0], [2.3, 0.85, 0], [2.8, 0.5, 0]]
  degree: 3
  capture_radius: 0.12
fit: {tolerance: 2.0e-3}
"""

PULL = """\
# Pull the top cap of the unit sphere up and twist it; the bottom half stays fixed.
input: scans/sphere.ply
output: out/sphere_pulled.ply
regions:
  units: model
  fixed:  [{plane: {point: [0, 0, -0.1], normal: [0, 0, -1]}}]
  handle: [{sphere: {center: [0, 0, 1], radius: 0.45}}]
handle:
  transform:
    pivot: centroid
    scale: [1.2, 1.2, 1.0]
    rotate: {axis: [0, 0, 1], degrees: 45}
    translate: [0, 0, 0.6]
fit: {tolerance: 1.0e-3}
"""

RUBBER_SHEET = """\
# Rubber-sheeting: warp a drifted terrain scan onto 12 surveyed control points. Each row of
# scans/gcp.csv is a pair: x,y,z where the point lies in the scan -> X,Y,Z surveyed (metres).
input: scans/drifted_scan.ply
output: out/warped.ply
points:
  pairs: {file: scans/gcp.csv}
  smoothing: 0            # 0: through every pair exactly; > 0: least squares (scipy's meaning)
  # check_pairs: {file: check.csv}   # held out of the fit, only reported
render:
  output: out/warped.png
  up: +z
  elevation: 50
  color: elevation        # the drifted scan has no colours of its own
"""
