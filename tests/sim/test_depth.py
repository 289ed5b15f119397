"""Tests of sim.depth: depth back-projection and the obstacle memory."""

from __future__ import annotations

import numpy as np
import pytest

from sim.cameras import CameraSpec, backproject
from sim.depth import ObstacleMemory, depth_to_points
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


def test_depth_to_points_matches_per_pixel_backprojection():
    spec = SPECS[0]
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 6.0, (spec.height_px, spec.width_px)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0.0  # invalid pixels are skipped
    pts = depth_to_points(depth, spec, stride=1)
    ref = []
    for r in range(spec.height_px):
        for c in range(spec.width_px):
            if depth[r, c] > 0:
                pc = backproject(np.array([c + 0.5, r + 0.5]), np.float64(depth[r, c]), spec.K)
                ref.append(spec.T_base_cam[:3, :3] @ pc + spec.T_base_cam[:3, 3])
    np.testing.assert_allclose(pts, np.array(ref), atol=1e-9)
    with pytest.raises(ValueError, match="shape"):
        depth_to_points(depth[:-1], spec)


def test_memory_keeps_points_for_memory_s_and_drops_what_is_seen_through():
    mem = ObstacleMemory(memory_s=1.0, voxel_m=0.1)
    p = np.array([[2.0, 0.0, 1.0], [2.02, 0.01, 1.0], [0.0, 3.0, 1.0]])
    mem.update(p, 0.0)
    assert len(mem) == 2  # the first two share a voxel
    mem.update(np.zeros((0, 3)), 0.5)
    assert len(mem) == 2
    mem.update(np.array([[0.0, 3.0, 1.0]]), 0.9)  # re-observed: refreshed
    mem.update(np.zeros((0, 3)), 1.2)
    assert len(mem) == 1 and mem.xyz[0, 1] == pytest.approx(3.0)
    # a point 2 m ahead: a wall at 4 m behind it clears it, a wall at 1.5 m in front of it hides it
    mem = ObstacleMemory(memory_s=5.0, voxel_m=0.1)
    mem.update(np.array([[2.0, 0.2, 1.0]]), 0.0)
    far = [wall_depth(s, 4.0) for s in SPECS]
    near = [wall_depth(s, 1.5) for s in SPECS]
    assert mem.seen_through(far, SPECS, (0.0, 0.0, 0.0), 0.25).tolist() == [True]
    assert mem.seen_through(near, SPECS, (0.0, 0.0, 0.0), 0.25).tolist() == [False]
    # behind the robot no camera sees it
    assert mem.seen_through(far, SPECS, (4.0, 0.2, 0.0), 0.25).tolist() == [False]
