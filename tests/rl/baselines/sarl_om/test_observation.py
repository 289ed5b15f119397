"""SARL*-OM's observation: CrowdNav's joint state, the angular map of the static scan."""

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from rl.baselines import sarl_om as S
from sim.env import CrowdNavEnv, SimConfig
from tests.rl.baselines.sarl_om.helpers import OC, make_scene


def test_joint_state_is_crowdnav_rotate():
    """Goal straight to the left (+y): the goal frame is the robot frame turned by +90°."""
    human = [[1.0, 2.0, 0.5, 0.0, 0.25]]  # robot frame: 1 m ahead, 2 m left, walking forward
    sc = make_scene(goal=(0.0, 3.0), humans=human, speed=0.8)
    js = S.current_state(sc, OC)
    np.testing.assert_allclose(js["self"][0], [3.0, 1.0, -math.pi / 2, 0.3, 0.0, -0.8], atol=1e-6)
    # in the goal frame x' = y, y' = -x
    np.testing.assert_allclose(js["humans"][0, 0], [2.0, -1.0, 0.0, -0.5, 0.25, math.sqrt(5), 0.55], atol=1e-6)
    assert js["mask"][0].tolist() == [1.0] + [0.0] * (OC.max_humans - 1)
    assert not js["humans"][0, 1:].any()


def test_angular_map_of_a_wall_and_its_scan():
    """A wall 1 m ahead across the robot's path: the sectors straight ahead are the closest, the rear is free."""
    scene = {"name": "wall", "split": "train", "description": "test: a wall", "bounds": [0.0, 8.0, 0.0, 8.0],
             "obstacles": [{"box": {"center": [5.1, 4.0], "size": [0.2, 6.0]}}],
             "start_goal": {"distance_m": [1.0, 1.3], "clearance_m": 0.5}}
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "wall.yaml"
        path.write_text(yaml.safe_dump(scene))
        env = CrowdNavEnv(config=replace(SimConfig(), scene=str(path), density=0.0, obs_mode="state"))
        env.reset(seed=0)
        env.robot = np.array([4.0, 4.0, 0.0])  # wall face at x = 5.0: 1 m ahead
        env.goal = np.array([6.5, 4.0])  # behind the wall, straight ahead
        sc = S.perceive(env, None, OC)
    assert np.abs(sc.hits[:, 0] - 1.0).max() < 1e-3  # every hit is on the wall face
    om = S.current_state(sc, OC)["om"][0]
    ahead = OC.om_sectors // 2  # sector starting at angle 0 (goal direction)
    assert om[ahead] == pytest.approx(1 - 1.0 / OC.om_range_m, abs=1e-3)
    assert om.argmax() in (ahead - 1, ahead)  # the nearest sectors border the goal direction
    assert not om[: OC.om_sectors // 4].any() and not om[-OC.om_sectors // 4 + 1:].any()  # behind: free
    # the lookahead's collision test sees the wall
    r, done = S.reward(sc, np.array([[0.75, 0.0], [0.0, 0.0]]), np.zeros((0, 2)), 2.5, 0.1, OC)
    assert done.tolist() == [True, False] and r[0] == OC.collision_penalty
