"""SARL*-OM's reward: the danger zones."""

from dataclasses import replace

import numpy as np

from rl.baselines import sarl_om as S
from tests.rl.baselines.sarl_om.helpers import OC, make_scene


def test_danger_zone_in_front_of_a_fast_walker_not_behind():
    walker = [[0.0, 0.0, 1.3, 0.0, 0.25]]  # at the origin, walking +x at 1.3 m/s
    sc = make_scene(goal=(0.0, 5.0), humans=walker)
    front, back = np.array([[1.2, 0.0]]), np.array([[-1.2, 0.0]])
    depth = S.danger_depth(np.stack([front, back]), np.array([[1.3, 0.0]]), np.array([0.25]), 0.3, OC)
    assert depth[0, 0] > 0.3 and depth[1, 0] == 0.0
    (r_front,), _ = S.reward(sc, front, sc.humans[:, :2], 5.14, 0.1, replace(OC, progress_weight=0.0))
    (r_back,), _ = S.reward(sc, back, sc.humans[:, :2], 5.14, 0.1, replace(OC, progress_weight=0.0))
    assert r_front < 0.0 and r_back == 0.0
    # a standing human's zone is a small full circle (every side, 0.75 m reach); a walker's is a narrow long sector
    sides = np.array([[[0.7, 0.0]], [[-0.7, 0.0]], [[0.0, 0.7]], [[0.0, 1.0]]])
    still = S.danger_depth(sides, np.zeros((1, 2)), np.array([0.25]), 0.3, OC)[:, 0]
    walking = S.danger_depth(sides, np.array([[1.3, 0.0]]), np.array([0.25]), 0.3, OC)[:, 0]
    assert (still[:3] > 0).all() and still[3] == 0.0
    assert walking[0] > still[0] and walking[1] == walking[2] == 0.0
