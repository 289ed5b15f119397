"""Training DRL-VO (package docstring): the expert's episodes as DRL-VO observations, the behaviour-cloning warm
start, then SB3 PPO on envs with DRL-VO's observation and reward."""

from __future__ import annotations

import functools
import math
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor
from torch import nn
from tqdm import tqdm

from pipeline.core.artifacts import atomic_save_npz
from pipeline.core.device import resolve_device
from rl.baselines.common import (
    collect_expert_episodes,
    load_baseline,
    save_baseline,
    save_curve_point,
    training_pairs,
)
from rl.baselines.drl_vo.configuration import NAME, Config, RewardConfig
from rl.baselines.drl_vo.model import build_policy, describe_inputs, policy_kwargs
from rl.baselines.drl_vo.observation import Observer
from rl.callbacks import checkpoint_callback, learn_with_critic_warmup, progress_callback, save_ppo
from rl.teacher import SceneMixEnv, curriculum_callback, discounted, ppo_kwargs
from rl.vec_env import BatchedSubprocVecEnv


def inputs(cfg) -> list[Path]:
    """DRL-VO needs nothing but the simulator."""
    return []


class DRLVOEnv(gym.Wrapper):
    """A crowd env (``CrowdNavEnv`` or ``rl.teacher.SceneMixEnv``, continuous actions) with DRL-VO's observations and
    reward; ``info["drl_vo"]`` holds the reward terms, ``info["is_success"]`` the outcome at the end."""

    def __init__(self, env: gym.Env, sensors: dict[str, float], reward: RewardConfig) -> None:
        super().__init__(env)
        self.observer = Observer(**sensors)
        self.reward_cfg = reward
        self.observation_space = self.observer.space

    @property
    def crowd_env(self):
        """The :class:`sim.env.CrowdNavEnv` of the current episode."""
        return getattr(self.env, "current", self.env)

    def set_pool(self, pairs: list[tuple[str, float]]) -> None:
        """The (scene, density) pool of a :class:`rl.teacher.SceneMixEnv` (the curriculum calls this)."""
        self.env.set_pool(pairs)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        _, info = self.env.reset(seed=seed, options=options)
        self.observer.reset(self.crowd_env)
        return self.observer(self.crowd_env), info

    def step(self, action):
        base = self.crowd_env
        d_prev = base.d_goal
        _, _, term, trunc, info = self.env.step(action)
        obs = self.observer(base)
        terms = self.observer.reward_terms(base, self.reward_cfg, d_prev, info["outcome"])
        info["drl_vo"] = terms
        if term or trunc:
            info["is_success"] = info["outcome"] == "success"
        return obs, terms["total"], term, trunc, info


class _ExpertObserver(Observer):
    """The observer of the expert's episodes, adding ``prev_reward``: DRL-VO's reward of the step into this state
    (NaN at the first step) — the value targets of the warm start."""

    def __init__(self, sensors: dict[str, float], reward: RewardConfig) -> None:
        super().__init__(**sensors)
        self.reward_cfg = reward
        self.d_goal_prev = math.nan

    def reset(self, env, obs: dict | None = None) -> None:
        super().reset(env, obs)
        self.d_goal_prev = math.nan

    def __call__(self, env, obs: dict | None = None, target: np.ndarray | None = None) -> dict[str, np.ndarray]:
        out = dict(super().__call__(env, obs, target))
        first = math.isnan(self.d_goal_prev)
        out["prev_reward"] = np.float32(math.nan if first else
                                        self.reward_terms(env, self.reward_cfg, self.d_goal_prev, None)["total"])
        self.d_goal_prev = env.d_goal
        return out


def _returns(data: dict[str, np.ndarray], arrival: float, gamma: float) -> np.ndarray:
    """Discounted DRL-VO returns of the expert's steps: step t's reward is ``prev_reward`` of step t+1; the last step
    of an episode gets its terminal reward (+arrival on success, −arrival on a collision or a timeout)."""
    out = np.zeros(len(data["done"]), np.float32)
    ends = np.flatnonzero(data["done"]) + 1
    for s, e in zip(np.r_[0, ends[:-1]], ends, strict=True):
        last = arrival if data["success"][e - 1] else -arrival
        out[s:e] = discounted([*data["prev_reward"][s + 1:e].tolist(), last], gamma)
    return out


def _clone(policy: ActorCriticPolicy, data: dict[str, np.ndarray], epochs: int, batch: int, lr: float, seed: int,
           progress: bool) -> list[dict[str, float]]:
    """Behaviour cloning: Gaussian negative log-likelihood of the expert's actions (mean and log-std) + 0.5 · MSE of
    the value on the DRL-VO returns divided by their variance (returns span ±20 and more: unscaled, the value's
    gradient would drown the policy's in the shared extractor). On the policy's device. One row per epoch:
    ``{"epoch", "nll", "action_mae", "value_loss"}`` (value_loss: the unscaled MSE)."""
    keys = tuple(policy.observation_space.spaces)
    dev = policy.device
    n = len(data["action"])
    g = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(policy.parameters(), lr=lr)
    v_scale = 1.0 / max(float(np.var(data["return"])), 1.0)
    policy.set_training_mode(True)
    rows = []
    for epoch in tqdm(range(epochs), desc="drl_vo: behaviour cloning", unit="epoch", disable=not progress,
                      dynamic_ncols=True):
        tot = {"nll": 0.0, "action_mae": 0.0, "value_loss": 0.0}
        for idx in torch.randperm(n, generator=g).split(batch):
            idx = np.sort(idx.numpy())
            obs = {k: torch.as_tensor(data[k][idx]).to(dev) for k in keys}
            act = torch.as_tensor(data["action"][idx], dtype=torch.float32).to(dev)
            latent_pi, latent_vf = policy.mlp_extractor(policy.extract_features(obs))
            mean = policy.action_net(latent_pi)
            nll = -policy.action_dist.proba_distribution(mean, policy.log_std).log_prob(act).mean()
            v_loss = nn.functional.mse_loss(policy.value_net(latent_vf).flatten(),
                                            torch.as_tensor(data["return"][idx]).to(dev))
            opt.zero_grad()
            (nll + 0.5 * v_scale * v_loss).backward()
            nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
            opt.step()
            tot["nll"] += nll.item() * len(idx)
            tot["value_loss"] += v_loss.item() * len(idx)
            tot["action_mae"] += float((mean.detach() - act).abs().mean()) * len(idx)
        rows.append({"epoch": epoch, **{k: v / n for k, v in tot.items()}})
    policy.set_training_mode(False)
    return rows


def _make_env(sim_cfg, pairs: list[tuple[str, float]], sensors: dict[str, float], reward: RewardConfig) -> DRLVOEnv:
    return DRLVOEnv(SceneMixEnv(sim_cfg, pairs, obs_mode="privileged", action_type="continuous"), sensors, reward)


def _log_callback(log):
    """Logs the mean episode return, length and success rate of the last episodes after every rollout."""
    class Curves(BaseCallback):
        def _on_step(self) -> bool:
            return True

        def _on_rollout_end(self) -> None:
            eps = list(self.model.ep_info_buffer)
            if eps:
                log.add("drl_vo_ppo", self.num_timesteps, ep_return=np.mean([e["r"] for e in eps]),
                        ep_len=np.mean([e["l"] for e in eps]),
                        success_rate=np.mean([float(e.get("is_success", 0.0)) for e in eps]))

    return Curves()


def _curve_callback(budgets: list[int], save) -> BaseCallback:
    """Calls ``save(policy, steps)`` once the PPO step count reaches each of ``budgets`` (the learning curve)."""
    class Curve(BaseCallback):
        def _on_step(self) -> bool:
            for b in budgets:
                if self.num_timesteps >= b and self.num_timesteps - self.model.n_envs < b:
                    save(self.model.policy, b)
            return True

    return Curve()


def train(cfg, out: Path, log) -> dict[str, Any]:
    """Trains DRL-VO into ``out`` (package docstring: warm start, then PPO; resumable) and writes the final
    checkpoint. Returns the summary with its ``budget``."""
    c: Config = cfg.drl_vo
    c.validate()
    out = Path(out)
    pairs = training_pairs(cfg)
    sensors, net = c.sensors(), c.net()
    ppo = ppo_kwargs(c.ppo)
    episodes = cfg.teacher.bc_episodes if c.bc_episodes is None else c.bc_episodes
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    device = resolve_device(cfg.device, "train.device")  # cloning and PPO updates (the envs step on the CPU)
    wall: dict[str, float] = {}
    summary: dict[str, Any] = {}
    bc_dir = out / "bc"
    frames = 0
    if episodes and (bc_dir / "policy.json").is_file():  # resuming: the warm start is done
        policy, desc = load_baseline(bc_dir, NAME, build_policy)
        policy.to(device)
        summary["bc"] = desc["bc"]
        frames = int(desc["bc"]["frames"])
    else:
        torch.manual_seed(cfg.seed)
        policy = build_policy(net).to(device)
    if episodes and "bc" not in summary:
        t0 = time.perf_counter()
        data = collect_expert_episodes(cfg.sim, pairs, episodes, cfg.seed,
                                       functools.partial(_ExpertObserver, sensors, c.reward), cfg.workers,
                                       gamma=ppo["gamma"], progress=cfg.progress, desc="drl_vo: expert episodes")
        data["return"] = _returns(data, c.reward.arrival, ppo["gamma"])
        data = {k: data[k] for k in ("peds", "scan", "goal", "action", "return", "success", "done")}
        wall["expert_s"] = round(time.perf_counter() - t0, 1)
        frames = len(data["action"])
        bc_dir.mkdir(parents=True, exist_ok=True)
        atomic_save_npz(bc_dir / "data.npz", data)
        t0 = time.perf_counter()
        rows = _clone(policy, data, c.bc_epochs, c.bc_batch, c.bc_lr, cfg.seed, cfg.progress)
        wall["bc_s"] = round(time.perf_counter() - t0, 1)
        for r in rows:
            log.add("drl_vo_bc", r["epoch"], nll=r["nll"], action_mae=r["action_mae"], value_loss=r["value_loss"])
        expert_sr = float(np.mean(data["success"][data["done"]]))
        summary["bc"] = {"episodes": episodes, "frames": frames, "expert_success_rate": expert_sr,
                         "epochs": c.bc_epochs, "final": rows[-1], "wall_s": {k: wall[k] for k in ("expert_s", "bc_s")}}
        save_baseline(bc_dir, NAME, policy, net, describe_inputs(policy), {"expert_episodes": episodes,
                                                                        "expert_frames": frames}, bc=summary["bc"],
                      observer=sensors)
        del data
    robot = cfg.sim.robot
    extra = {"observer": sensors, "robot": {"v_max_mps": robot.v_max_mps, "omega_max_radps": robot.omega_max_radps},
             "reward": asdict(c.reward)}

    def curve_point(p: ActorCriticPolicy, steps: int) -> None:
        save_curve_point(out, NAME, p, net, describe_inputs(p), {"expert_episodes": episodes, "expert_frames": frames,
                                                                  "ppo_env_steps": steps}, steps, "ppo_env_steps",
                         **extra)

    ppo_steps = 0
    if c.ppo_steps > 0:
        sim_cfg = cfg.sim
        fns = [functools.partial(_make_env, sim_cfg, pairs, sensors, c.reward)] * c.n_envs
        venv = BatchedSubprocVecEnv(fns, start_method="fork") if c.subprocess and c.n_envs > 1 else DummyVecEnv(fns)
        venv = VecMonitor(venv, info_keywords=("is_success",))
        venv.seed(cfg.seed + 1)
        last = out / "ppo" / "last.zip"
        if last.exists():
            model = PPO.load(last, env=venv, device=device)
        else:
            model = PPO("MultiInputPolicy", venv, policy_kwargs=policy_kwargs(net), seed=cfg.seed, device=device,
                        verbose=0, tensorboard_log=str(out / "tb"), **ppo)
            model.policy.load_state_dict(policy.state_dict())
        done = model.num_timesteps
        if c.curve_steps and done == 0:
            curve_point(model.policy, 0)  # the warm start: the curve's first point
        t0 = time.perf_counter()
        cb = [curriculum_callback(cfg.teacher.curriculum, c.ppo_steps), checkpoint_callback(out / "ppo", model, 5_000),
              progress_callback(c.ppo_steps, "drl_vo PPO", cfg.progress), _log_callback(log),
              _curve_callback(c.curve_steps, curve_point)]
        # the cloned critic is poor: fitted on-policy before the actor moves (measured: the module's docstring)
        learn_with_critic_warmup(model, c.ppo_steps, c.critic_warmup_steps, cb, "ppo")
        wall["ppo_s"] = round(time.perf_counter() - t0, 1)
        summary["ppo_steps_per_s"] = round((model.num_timesteps - done) / max(wall["ppo_s"], 1e-9), 1)
        ppo_steps = int(model.num_timesteps)
        save_ppo(model, last)
        venv.close()
        policy = model.policy
        policy.set_training_mode(False)
    budget = {"expert_episodes": episodes, "expert_frames": frames, "bc_epochs": c.bc_epochs if episodes else 0,
              "ppo_env_steps": ppo_steps, "wall_s": wall}
    save_baseline(out, NAME, policy, net, describe_inputs(policy), budget, **extra)
    summary["budget"] = budget
    return summary
