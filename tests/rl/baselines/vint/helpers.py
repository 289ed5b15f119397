"""Shared helpers of the ViNT-style tests: a tiny network, the train config on the tests' dataset, a seeded
rollout of a checkpoint's driver (also run in a fresh process)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from rl.baselines.vint import Config, Driver
from rl.stage import TrainConfig
from tests.conftest import tiny_sim_config

TINY_NET = {"embed_dim": 32, "layers": 1, "heads": 2, "output_layers": [32, 16], "image_hw": [12, 16]}


class Log:
    def __init__(self) -> None:
        self.rows: list[tuple[str, int, dict]] = []

    def add(self, phase: str, step: int, **values: float) -> None:
        self.rows.append((phase, step, values))


def train_cfg(data_dir: Path, **vint) -> TrainConfig:
    v = Config(repo_id="icrowdnav/tiny", epochs=1, clip_len=8, clips_per_batch=2, val_fraction=0.5, **TINY_NET)
    return TrainConfig(data_dir=data_dir, variant="vint", seed=0, threads=1, progress=False, vint=replace(v, **vint))


def rollout(ckpt: str) -> list[list[float]]:
    """The driver's actions over the first steps of a seeded visual episode (tiny cameras)."""
    from sim.env import CrowdNavEnv

    torch.set_num_threads(1)
    driver = Driver(Path(ckpt))
    env = CrowdNavEnv(config=replace(tiny_sim_config(), density=0.1, obs_mode="visual"))
    obs, info = env.reset(seed=3)
    driver.reset(obs, info)
    actions = []
    for _ in range(8):
        a = driver.act(obs, info)
        actions.append(np.asarray(a, float).tolist())
        obs, _, term, trunc, info = env.step(a)
        if term or trunc:
            break
    env.close()
    return actions
