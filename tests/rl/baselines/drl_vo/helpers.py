"""Shared helpers of the DRL-VO tests: the empty test room, seeded episodes with a checkpoint's driver."""

from dataclasses import replace
from pathlib import Path

import numpy as np

from rl.baselines import drl_vo
from sim.env import CrowdNavEnv, SimConfig
from sim.wrappers import with_privileges

ROOT = Path(__file__).resolve().parents[4]
# an empty 8 x 8 m room, goals 2.5-3 m away: driving straight ahead reaches few of them (start heading ±0.5 rad off)
EMPTY_ROOM = {"name": "empty_room", "split": "train", "description": "test: an empty 8 x 8 m room",
              "bounds": [0.0, 8.0, 0.0, 8.0], "obstacles": [], "start_goal": {"distance_m": [2.5, 3.0],
                                                                              "clearance_m": 0.5}}
SEEDS = list(range(100, 110))


class Rows:
    """A ``log`` that keeps its rows."""

    def __init__(self) -> None:
        self.rows: list[tuple[str, int, dict]] = []

    def add(self, phase: str, step: int, **values: float) -> None:
        self.rows.append((phase, step, values))


def make_env(scene: str, density: float = 0.0, **over) -> CrowdNavEnv:
    return CrowdNavEnv(config=replace(SimConfig(), scene=scene, density=density, obs_mode="privileged",
                                      action_type="continuous", info_level="basic", **over))


def drive(ckpt: Path, scene: str, seed: int) -> tuple[str, list[list[float]]]:
    """One seeded episode with the checkpoint's driver: (outcome, actions)."""
    driver = drl_vo.Driver(ckpt)
    env = with_privileges(make_env(scene, max_episode_s=8.0), "privileged")  # as the benchmark gives it
    obs, info = env.reset(seed=seed)
    driver.reset(obs, info)
    actions = []
    while True:
        a = driver.act(obs, info)
        actions.append([float(x) for x in a])
        obs, _, term, trunc, info = env.step(a)
        if term or trunc:
            return info["outcome"], actions


def success_rate(ckpt: Path, scene: str) -> float:
    return float(np.mean([drive(ckpt, scene, s)[0] == "success" for s in SEEDS]))
