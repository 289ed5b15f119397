"""Shared helpers of the SARL*-OM tests: the empty test room, constructed scenes, greedy lookahead episodes."""

from dataclasses import replace
from pathlib import Path

import numpy as np

from rl.baselines import sarl_om as S
from sim.env import CrowdNavEnv

ROOT = Path(__file__).resolve().parents[4]
EMPTY_ROOM = {"name": "empty_room", "split": "train", "description": "test: an empty 6 x 6 m room",
              "bounds": [0.0, 6.0, 0.0, 6.0], "obstacles": [], "start_goal": {"distance_m": [1.0, 1.3],
                                                                              "clearance_m": 0.5}}
OC = S.Config()


class RecordingLog:
    """The training log ``S.train`` writes to, keeping every row ``(phase, step, values)`` of this instance."""

    def __init__(self) -> None:
        self.rows: list[tuple] = []

    def add(self, phase, step, **values) -> None:
        self.rows.append((phase, step, values))


def make_scene(goal=(3.0, 0.0), humans=(), hits=(), speed=0.0) -> S.Scene:
    return S.Scene(goal=np.asarray(goal, float), humans=np.asarray(humans, float).reshape(-1, 5),
                   hits=np.asarray(hits, float).reshape(-1, 2),
                   speed=speed, radius=0.3, v_pref=1.0, goal_radius=0.3)


def success_rate(model, oc, sim_cfg, seeds) -> tuple[float, list[int]]:
    env = CrowdNavEnv(config=replace(sim_cfg, obs_mode="state", action_type="discrete", info_level="basic"))
    wins = 0
    actions = []
    for s in seeds:
        ep = S.run_episode(env, model, oc, s, 0.0)
        wins += ep["outcome"] == "success"
        actions.append(ep["actions"])
    return wins / len(seeds), actions
