"""The privileged teacher: behaviour cloning of the privileged expert, then PPO with the paper's reward.

The teacher sees what the student cannot (robot state, the nearest pedestrians' true relative positions and
velocities, a range scan of the static map) and needs no rendering, so thousands of env steps per second run on two
cores. Training, on the *training* scenes only:

1. **Warm start** (``bc_episodes``): the privileged expert (:mod:`sim.expert`) drives episodes over every
   (scene, density) of the curriculum; the policy is trained by cross-entropy on its actions (mapped to the
   5 x 21 grid) and the value head by regression on the discounted returns of the paper's reward.
2. **PPO** (stable-baselines3, ``SubprocVecEnv`` on both cores, the paper's reward) continues from the warm start.
   A curriculum widens the (scene, density) pool with training progress (:class:`SceneMixEnv`). ``ppo_steps = 0``
   skips PPO (the teacher is then the cloned expert; the report says so).

Without the warm start, PPO alone learns an empty scene in a few thousand steps (tested) but needs millions of
steps for crowds — the paper's GPU budget, kept in the ``paper`` profile.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from pipeline.errors import ConfigError
from sim.env import CrowdNavEnv, SimConfig


@dataclass
class CurriculumStage:
    """Until ``until`` (fraction of the PPO steps) episodes are drawn from these scenes and densities."""

    until: float = 1.0
    scenes: list[str] = field(default_factory=lambda: ["hallway", "corner", "doorway", "cluttered_room", "open_crowd"])
    densities: list[float] = field(default_factory=lambda: [0.1, 0.2])


def curriculum_pairs(stage: CurriculumStage) -> list[tuple[str, float]]:
    return [(s, float(d)) for s in stage.scenes for d in stage.densities]


def check_curriculum(stages: list[CurriculumStage]) -> None:
    if not stages:
        raise ConfigError("teacher.curriculum: expected at least one stage")
    last = 0.0
    for k, st in enumerate(stages):
        if not st.scenes or not st.densities:
            raise ConfigError(f"teacher.curriculum[{k}]: expected non-empty scenes and densities")
        if not last < st.until <= 1.0:
            raise ConfigError(f"teacher.curriculum[{k}].until: expected increasing fractions in (0, 1], got "
                              f"{st.until}")
        last = st.until
    if abs(last - 1.0) > 1e-9:
        raise ConfigError(f"teacher.curriculum: the last stage must run until 1.0, got {last}")


class SceneMixEnv(gym.Env):
    """Discrete-action crowd env (privileged by default) drawing (scene, density) from a pool at every reset.

    One :class:`sim.env.CrowdNavEnv` per pair is built lazily; :meth:`set_pool` changes the pool (curriculum).
    """

    metadata = {"render_modes": []}

    def __init__(self, sim_cfg: SimConfig, pairs: list[tuple[str, float]], obs_mode: str = "privileged") -> None:
        super().__init__()
        self.sim_cfg = replace(sim_cfg, obs_mode=obs_mode, action_type="discrete", info_level="basic")
        self._envs: dict[tuple[str, float], CrowdNavEnv] = {}
        self.pairs = list(pairs)
        probe = self._env(self.pairs[0])
        self.observation_space = probe.observation_space
        self.action_space = probe.action_space
        self.current: CrowdNavEnv = probe
        self._rng = np.random.default_rng(0)

    def _env(self, pair: tuple[str, float]) -> CrowdNavEnv:
        if pair not in self._envs:
            self._envs[pair] = CrowdNavEnv(config=replace(self.sim_cfg, scene=pair[0], density=pair[1]))
        return self._envs[pair]

    def set_pool(self, pairs: list[tuple[str, float]]) -> None:
        self.pairs = [(s, float(d)) for s, d in pairs]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        pair = self.pairs[int(self._rng.integers(len(self.pairs)))]
        self.current = self._env(pair)
        return self.current.reset(seed=int(self._rng.integers(2**31 - 1)))

    @property
    def cfg(self) -> SimConfig:
        return self.current.cfg

    @property
    def cameras(self):
        return self.current.cameras

    def close(self) -> None:
        for e in self._envs.values():
            e.close()

    def step(self, action):
        return self.current.step(action)


# ------------------------------------------------------------------------------------------------ expert warm start
def expert_episode(args: tuple[SimConfig, str, float, int, float]) -> dict[str, np.ndarray]:
    """One privileged expert episode: observations, the expert's action indices, rewards, discounted returns."""
    from sim.expert import PrivilegedExpert

    sim_cfg, scene, density, seed, gamma = args
    env = CrowdNavEnv(config=replace(sim_cfg, scene=scene, density=density, obs_mode="privileged",
                                     action_type="discrete", info_level="basic"))
    expert = PrivilegedExpert()
    obs, _ = env.reset(seed=seed)
    expert.reset(env)
    rows: dict[str, list] = {k: [] for k in obs}
    actions, rewards = [], []
    outcome = "timeout"
    while True:
        a = env.encode_command(*expert.command(env))
        for k, v in obs.items():
            rows[k].append(v)
        actions.append(a)
        obs, r, term, trunc, info = env.step(a)
        rewards.append(r)
        if term or trunc:
            outcome = info["outcome"] or "timeout"
            break
    ret = np.zeros(len(rewards), np.float32)
    acc = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        acc = rewards[t] + gamma * acc * (0.0 if (t == len(rewards) - 1 and outcome != "timeout") else 1.0)
        ret[t] = acc
    out = {k: np.stack(v).astype(np.float32) for k, v in rows.items()}
    out["action"] = np.asarray(actions, np.int64)
    out["return"] = ret
    out["success"] = np.array([outcome == "success"])
    return out


def collect_expert(sim_cfg: SimConfig, pairs: list[tuple[str, float]], episodes: int, seed: int, gamma: float,
                   workers: int, progress: bool = True) -> dict[str, np.ndarray]:
    """``episodes`` expert episodes spread evenly over ``pairs`` (process pool), concatenated."""
    from tqdm import tqdm

    jobs = [(sim_cfg, *pairs[k % len(pairs)], seed + k, gamma) for k in range(episodes)]
    parts = []
    with ProcessPoolExecutor(max(1, workers)) as pool:
        for part in tqdm(pool.map(expert_episode, jobs), total=len(jobs), desc="teacher: expert episodes",
                         unit="ep", disable=not progress, dynamic_ncols=True):
            parts.append(part)
    keys = [k for k in parts[0] if k != "success"]
    data = {k: np.concatenate([p[k] for p in parts]) for k in keys}
    data["expert_success_rate"] = np.array(np.mean([p["success"][0] for p in parts]))
    return data


def behaviour_clone(policy, data: dict[str, np.ndarray], epochs: int, batch: int, lr: float, seed: int,
                    value_coef: float = 0.5, keys: tuple[str, ...] | None = None,
                    progress: bool = True) -> list[dict[str, float]]:
    """Cross-entropy on ``data["action"]`` (+ value regression on ``data["return"]`` when present).

    Returns one row per epoch: ``{"epoch", "bc_loss", "accuracy", "value_loss"}`` (means over the epoch).
    """
    from tqdm import tqdm

    keys = keys or tuple(policy.observation_space.spaces)
    n = len(data["action"])
    g = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(policy.parameters(), lr=lr)
    policy.set_training_mode(True)

    def take(idx: np.ndarray) -> dict[str, torch.Tensor]:  # per batch: the cache stays float16 numpy
        return {k: torch.as_tensor(data[k][idx], dtype=torch.float32) for k in keys}

    rows = []
    for epoch in tqdm(range(epochs), desc="behaviour cloning", unit="epoch", disable=not progress,
                      dynamic_ncols=True):
        perm = torch.randperm(n, generator=g).numpy()
        tot = {"bc_loss": 0.0, "accuracy": 0.0, "value_loss": 0.0}
        for s in range(0, n, batch):
            idx = np.sort(perm[s:s + batch])
            obs = take(idx)
            act_t = torch.as_tensor(data["action"][idx], dtype=torch.long)
            values, logp, _ = policy.evaluate_actions(obs, act_t)
            loss_bc = -logp.mean()
            loss = loss_bc
            if "return" in data:
                loss_v = torch.nn.functional.mse_loss(values.flatten(),
                                                      torch.as_tensor(data["return"][idx], dtype=torch.float32))
                loss = loss + value_coef * loss_v
                tot["value_loss"] += loss_v.item() * len(idx)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
            opt.step()
            with torch.no_grad():
                pred = policy.get_distribution(obs).get_actions(True)
            tot["bc_loss"] += loss_bc.item() * len(idx)
            tot["accuracy"] += float((pred == act_t).float().sum())
        rows.append({"epoch": epoch, **{k: v / n for k, v in tot.items()}})
    policy.set_training_mode(False)
    return rows


@torch.no_grad()
def bc_loss(policy, data: dict[str, np.ndarray], batch: int = 1024) -> float:
    """Mean negative log-likelihood of ``data["action"]`` under ``policy`` (no gradient)."""
    keys = tuple(policy.observation_space.spaces)
    n = len(data["action"])
    tot = 0.0
    for s in range(0, n, batch):
        obs = {k: torch.as_tensor(data[k][s:s + batch], dtype=torch.float32) for k in keys}
        _, logp, _ = policy.evaluate_actions(obs, torch.as_tensor(data["action"][s:s + batch]))
        tot += float(-logp.sum())
    return tot / max(n, 1)


# ---------------------------------------------------------------------------------------------------------- PPO
def make_vec_env(sim_cfg: SimConfig, pairs: list[tuple[str, float]], n_envs: int, seed: int, subprocess: bool):
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    fns = [lambda: SceneMixEnv(sim_cfg, pairs) for _ in range(n_envs)]
    venv = SubprocVecEnv(fns, start_method="fork") if subprocess and n_envs > 1 else DummyVecEnv(fns)
    venv.seed(seed)
    return venv


def curriculum_callback(stages: list[CurriculumStage], total_steps: int, start_steps: int = 0):
    """An SB3 callback that sets each env's (scene, density) pool from the training progress."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Curriculum(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.stage = -1

        def _on_step(self) -> bool:
            frac = (self.num_timesteps - start_steps) / max(total_steps, 1)
            k = next((i for i, st in enumerate(stages) if frac < st.until), len(stages) - 1)
            if k != self.stage:
                self.stage = k
                self.training_env.env_method("set_pool", curriculum_pairs(stages[k]))
                self.logger.record("curriculum/stage", k)
            return True

    return Curriculum()


def stage_pairs_all(stages: list[CurriculumStage]) -> list[tuple[str, float]]:
    seen: dict[tuple[str, float], None] = {}
    for st in stages:
        for p in curriculum_pairs(st):
            seen[p] = None
    return list(seen)


def ppo_kwargs(ppo: dict[str, Any]) -> dict[str, Any]:
    """SB3 PPO keyword arguments from a config section (the paper's values as defaults)."""
    keys = ("n_steps", "batch_size", "n_epochs", "learning_rate", "gamma", "gae_lambda", "clip_range",
            "ent_coef", "vf_coef", "max_grad_norm", "target_kl")
    out = {"n_steps": 1024, "batch_size": 128, "n_epochs": 6, "learning_rate": 5e-4, "gamma": 0.99,
           "gae_lambda": 0.95, "clip_range": 0.2, "ent_coef": 0.0, "vf_coef": 0.5, "max_grad_norm": 0.5}
    unknown = sorted(set(ppo) - set(keys))
    if unknown:
        raise ConfigError(f"ppo: unknown option(s) {unknown}; options: {list(keys)}")
    out.update({k: ppo[k] for k in keys if k in ppo and ppo[k] is not None})
    for k in ("n_steps", "batch_size", "n_epochs"):
        out[k] = int(out[k])
    return out

