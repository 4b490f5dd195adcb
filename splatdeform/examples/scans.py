"""Seeded synthetic scans: a bumpy bar and a sphere (oriented surfel clouds).

The examples (``splatdeform example``), the tests and the demo make their scans here; a seed
gives the same points, byte for byte, on every machine.
"""

from __future__ import annotations

import numpy as np

from splatdeform.model import PointModel


def _surfel_radius(n_points: int, area: float) -> np.ndarray:
    return np.full(n_points, 0.75 * np.sqrt(area / n_points))


def bumpy_bar(n_points: int = 20000, *, length: float = 4.0, radius: float = 0.5,
              bumps: float = 0.04, seed: int = 0) -> PointModel:
    """A bumpy cylinder along x (x in [0, length]) with end caps.

    Returns an oriented surfel cloud: positions/normals (N, 3) float64, radius (N,), colors
    (N, 3) uint8.
    """
    rng = np.random.default_rng(seed)
    side_area = 2 * np.pi * radius * length
    cap_area = np.pi * radius**2
    n_cap = max(int(n_points * cap_area / (side_area + 2 * cap_area)), 1)
    n_side = n_points - 2 * n_cap
    x = rng.uniform(0, length, n_side)
    theta = rng.uniform(0, 2 * np.pi, n_side)
    r = radius * (1 + bumps * np.sin(5 * theta) * np.sin(3 * np.pi * x / length))
    side = np.stack([x, r * np.cos(theta), r * np.sin(theta)], axis=1)
    # normal of the bumpy surface: gradient of F = rho - r(theta, x)
    dr_dtheta = radius * bumps * 5 * np.cos(5 * theta) * np.sin(3 * np.pi * x / length)
    dr_dx = radius * bumps * np.sin(5 * theta) * (3 * np.pi / length) * np.cos(3 * np.pi * x /
                                                                              length)
    e_rho = np.stack([np.zeros_like(x), np.cos(theta), np.sin(theta)], axis=1)
    e_theta = np.stack([np.zeros_like(x), -np.sin(theta), np.cos(theta)], axis=1)
    e_x = np.array([1.0, 0, 0])
    side_n = e_rho - (dr_dtheta / r)[:, None] * e_theta - dr_dx[:, None] * e_x
    caps, caps_n = [], []
    for x0, nx in ((0.0, -1.0), (length, 1.0)):
        rr = radius * np.sqrt(rng.uniform(0, 1, n_cap)) * 0.98
        tt = rng.uniform(0, 2 * np.pi, n_cap)
        caps.append(np.stack([np.full(n_cap, x0), rr * np.cos(tt), rr * np.sin(tt)], axis=1))
        caps_n.append(np.tile([nx, 0.0, 0.0], (n_cap, 1)))
    positions = np.concatenate([side, *caps])
    normals = np.concatenate([side_n, *caps_n])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    shade = (120 + 100 * positions[:, 0] / length).astype(np.uint8)
    colors = np.stack([shade, np.full_like(shade, 140), 255 - shade], axis=1)
    return PointModel(positions=positions, normals=normals, colors=colors,
                      radius=_surfel_radius(len(positions), side_area + 2 * cap_area),
                      kind="surfel_radius")


def sphere(n_points: int = 10000, *, radius: float = 1.0, seed: int = 0) -> PointModel:
    """Points uniformly on a sphere with outward normals and surfel radii: positions/normals
    (N, 3) float64, radius (N,), colors (N, 3) uint8."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n_points, 3))
    normals = v / np.linalg.norm(v, axis=1, keepdims=True)
    colors = np.clip((normals * 0.5 + 0.5) * 255, 0, 255).astype(np.uint8)
    return PointModel(positions=normals * radius, normals=normals.copy(), colors=colors,
                      radius=_surfel_radius(n_points, 4 * np.pi * radius**2),
                      kind="surfel_radius")
