"""Tests of sim.depth: depth back-projection and the obstacle memory."""

from __future__ import annotations

import numpy as np
import pytest

from sim.cameras import backproject
from sim.depth import ObstacleMemory, depth_to_points
from tests.sim.helpers_depth import SPECS, wall_depth


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
