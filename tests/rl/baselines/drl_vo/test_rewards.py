"""DRL-VO's reward: the velocity-obstacle heading term, the terminal and shaping terms."""

import math

import numpy as np
import pytest

from rl.baselines import drl_vo


@pytest.mark.parametrize(("ped", "blocked"), [
    ([2.0, 0.0, 0.0, 0.0], True),  # standing on the way to the sub-goal
    ([2.0, 3.0, 0.0, 0.0], False),  # standing off to the side
    ([2.0, 2.0, 0.0, -1.0], True),  # crossing toward the robot's path: relative velocity (1, 1) points at it
    ([2.0, 2.0, 0.0, 1.0], False),  # walking away from the path: relative velocity (1, −1) misses it
    ([8.0, 0.0, 0.0, 0.0], False),  # beyond the 7 m range
])
def test_vo_reward_penalises_heading_into_a_velocity_obstacle(ped, blocked):
    cfg = drl_vo.RewardConfig()
    goal = np.array([2.0, 0.0])  # the sub-goal straight ahead; the robot moves at 1 m/s
    heading = drl_vo.vo_heading(goal, np.array([ped]), 1.0, 0.3, cfg.vo_range_m, cfg.vo_headings)
    r = drl_vo.reward_terms(cfg, None, 3.0, 3.0, 10.0, 0.0, heading, 0.3)
    if blocked:
        assert abs(heading) > 0.3  # the nearest free heading is off the cone
        assert r["heading"] < cfg.angle * (cfg.angle_thresh_rad - 0.3)
    else:
        assert heading == 0.0
        assert r["heading"] == pytest.approx(cfg.angle * cfg.angle_thresh_rad)
    assert r["total"] == pytest.approx(r["heading"])  # no progress, no obstacle, no rotation


def test_reward_terminal_and_shaping_terms():
    cfg = drl_vo.RewardConfig()
    assert drl_vo.reward_terms(cfg, "success", 0.2, 0.3, 10.0, 0.0, 0.0, 0.3)["goal"] == 20.0
    assert drl_vo.reward_terms(cfg, "timeout", 2.0, 2.0, 10.0, 0.0, 0.0, 0.3)["goal"] == -20.0
    assert drl_vo.reward_terms(cfg, "collision_pedestrian", 2.0, 2.0, 0.2, 0.0, 0.0, 0.3)["collision"] == -20.0
    r = drl_vo.reward_terms(cfg, None, 1.9, 2.0, 0.5, 1.5, 0.0, 0.3)
    assert r["goal"] == pytest.approx(0.32) and r["collision"] == pytest.approx(-0.2 * 0.4)
    assert r["rotation"] == pytest.approx(-0.15)
    assert drl_vo.vo_heading(np.array([1.0, 1.0]), np.zeros((0, 5)), 1.0, 0.3, 7.0, 60) == pytest.approx(math.pi / 4)
