"""Exact depth images for the depth and DWA tests: a flat wall in front of the robot (base frame)."""

from __future__ import annotations

import numpy as np

from sim.cameras import CameraSpec
from sim.env import CameraConfig

SPECS = CameraConfig(width_px=64, height_px=48).specs()


def wall_depth(spec: CameraSpec, wall_x_m: float | None, floor: bool = True) -> np.ndarray:
    """Exact z-depth image of a camera on the robot looking at an infinite wall ``x = wall_x_m`` (base frame)
    standing on the floor ``z = 0`` (0 where the ray hits neither within the valid depth range)."""
    h, w = spec.height_px, spec.width_px
    vv, uu = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    k = spec.K
    ray_c = np.stack([(uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], np.ones_like(uu)], -1)  # z = 1
    t = spec.T_base_cam
    ray_b = ray_c @ t[:3, :3].T
    o = t[:3, 3]
    depth = np.full((h, w), np.inf)
    if wall_x_m is not None:
        lam = (wall_x_m - o[0]) / np.where(ray_b[..., 0] > 1e-9, ray_b[..., 0], np.nan)
        depth = np.where(np.isfinite(lam) & (lam > 0), lam, depth)
    if floor:
        mu = -o[2] / np.where(ray_b[..., 2] < -1e-9, ray_b[..., 2], np.nan)
        depth = np.where(np.isfinite(mu) & (mu > 0) & (mu < depth), mu, depth)
    valid = (depth >= spec.min_depth_m) & (depth <= spec.max_depth_m)
    return np.where(valid, depth, 0.0).astype(np.float32)
