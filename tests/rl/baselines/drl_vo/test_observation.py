"""DRL-VO's observation: the kinematic map and the lidar history."""

import math

import numpy as np
import torch

from rl.baselines import drl_vo
from tests.rl.baselines.drl_vo.helpers import make_env


def test_kinematic_map_puts_a_pedestrian_in_its_cell_with_its_robot_frame_velocity():
    """A pedestrian 4.06 m ahead, 1.44 m left of a robot facing +y (world), walking at 1 m/s along +x (world): its
    robot-frame velocity is (0, −1) m/s, in cell (⌊4.06 / 0.125⌋, ⌊(5 − 1.44) / 0.125⌋) = (32, 28); every other
    pedestrian is behind the robot, outside the map."""
    env = make_env("open_crowd", 0.1)
    env.reset(seed=0)
    assert env.crowd.n >= 2
    env.robot = np.array([env.robot[0], env.robot[1], math.pi / 2])
    x, y = env.robot[:2]
    forward, left = 4.06, 1.44
    env.crowd.pos[:] = np.stack([x + 0.7 * np.arange(env.crowd.n) - 3.0, np.full(env.crowd.n, y - 2.0)], -1)  # behind
    env.crowd.pos[0] = [x - left, y + forward]  # facing +y: forward = +y world, left = −x world
    env.crowd.vel[:] = 0.5
    env.crowd.vel[0] = [1.0, 0.0]
    observer = drl_vo.Observer(**drl_vo.Config().sensors())
    observer.reset(env)
    o = observer(env)
    assert observer.space.contains({k: v.astype(np.float32) for k, v in o.items()})
    m = drl_vo.kinematic_map(torch.as_tensor(o["peds"])[None])[0].numpy()
    assert m.shape == (2, 80, 80)
    np.testing.assert_allclose(m[:, 32, 28], [0.0, -1.0], atol=1e-5)
    m[:, 32, 28] = 0.0
    assert not m.any(), "cells other than the pedestrian's are set"
    # the lidar history map: 10 identical scans after a reset, min <= mean per bin, within range; the pedestrian's
    # bin (bearing 19.5° left of the heading, 2.25° bins from the right) returns at most its body surface
    s = o["scan"]
    assert s.shape == (20, 80) and (s >= 0).all() and (s <= 30.0).all()
    np.testing.assert_array_equal(s[0::2], np.repeat(s[:1], 10, 0))
    assert (s[0::2] <= s[1::2] + 1e-5).all()
    b = int((math.degrees(math.atan2(left, forward)) + 90.0) // 2.25)
    assert s[-2, b] <= math.hypot(forward, left) - env.crowd.radius[0] + 1e-3
    env.step(env.encode_command(0.0, 0.0))
    s2 = observer(env)["scan"]
    np.testing.assert_array_equal(s2[:-2], s[2:])  # the history shifts by one scan
