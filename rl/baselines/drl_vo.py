"""DRL-VO (Xie & Dames, "DRL-VO: Learning to Navigate Through Crowded Dynamic Scenes Using Velocity Obstacles",
IEEE T-RO 2023; code: github.com/TempleRAIL/drl_vo_nav), rebuilt for our simulator.

**What it observes** (built from the ``env`` object each step, never from the ``obs`` dict), in the robot frame
(x forward, y left):

* the *pedestrian kinematic map* — ``2 x 80 x 80`` (vx, vy in m/s), 0.125 m cells over x ∈ [0, 10] m,
  y ∈ [−5, 5] m (row = ⌊x / 0.125⌋, column = ⌊(5 − y) / 0.125⌋, the original's extent and resolution): each
  tracked pedestrian writes its robot-frame velocity into the cell of its centre. Tracks are a *perfect tracker*:
  true positions and velocities of every pedestrian within ``tracker_range_m`` (12 m: the whole map and the 7 m
  velocity-obstacle range), without occlusion — as the original's simulation training read pedsim's ground truth.
  The observation carries the tracks inside the map (``peds``: K x 5 [x, y, vx, vy, present]); the network
  scatters them into the map (:func:`kinematic_map`, one implementation for training, driving and the tests).
* the *lidar history map* — the last 10 scans (1 s at 10 Hz, as the original) of a 180° lidar with 720 beams
  (0.25°, the original's Hokuyo slice) and 30 m range that sees obstacles and pedestrian bodies
  (:func:`rl.baselines.common.lidar_scan`, ~0.7 ms a scan); each scan is min- and average-pooled over 9-beam bins
  into two 80-vectors (``scan``: 20 x 80, oldest first), tiled 4 times into an 80 x 80 map by the network.
* the *sub-goal* — the pure-pursuit point 2 m ahead on the global shortest path on the static map
  (:class:`rl.baselines.common.GlobalPath`), robot frame (m). A waypoint (long-horizon runs) replaces the goal as
  the path's target.

Inputs are scaled as the original's MaxAbsScaler: velocities / 2 m/s, sub-goal / 2 m, ranges to [−1, 1] over 30 m.

**Network** (:class:`DRLVOExtractor`, an SB3 features extractor): the original's early-fusion ResNet — the lidar map
and the kinematic map stacked as 3 channels; stem conv 3x3 + max-pool; 2 bottlenecks (expansion 2); a stride-2
bottleneck and a 1x1-3x3-1x1 block with a stride-2 shortcut from the first stage; a stride-2 bottleneck and a
1x1-3x3-1x1 block with a stride-4 shortcut from the stem; global average pool; the sub-goal concatenated; FC 256 +
ReLU. Heads as the original: policy MLP [256], value MLP [128], a diagonal Gaussian over the normalised (v, ω)
(SB3 PPO). Our sizes (default ``width`` 16): channels 16 → 32 → 64 → 128 over 20 → 10 → 5 cells, 0.19 M
parameters in the extractor.

**Reward** (:func:`reward_terms`, in :class:`DRLVOEnv`, the original's terms and constants):
``r = r_g + r_c + r_w + r_t`` with r_g = +20 at the goal, −20 on a timeout, else 3.2 · (progress toward the goal,
m); r_c = −20 on a collision, else −0.2 · (0.9 − d_scan) when the nearest lidar return d_scan < 3 ρ_robot = 0.9 m;
r_w = −0.1 |ω| when |ω| > 1 rad/s; r_t = 0.6 · (π/6 − |θ_vo|), where θ_vo is the heading closest to the sub-goal
direction whose velocity (the robot's current speed along it) lies outside the velocity obstacle — the cone of
half-angle asin(3 ρ_robot / d) toward each pedestrian within 7 m, relative to its velocity — of every
pedestrian (π/2 if none is free; the sub-goal direction when no pedestrian is within 7 m) (:func:`vo_heading`).

**Training** (:func:`train`, on the training scenes of the teacher's curriculum only): a behaviour-cloning warm start
on the privileged expert's episodes (as many as the teacher's ``bc_episodes`` by default; Gaussian
log-likelihood of the expert's action + value regression on the discounted DRL-VO returns), then SB3 PPO with
continuous actions and the DRL-VO reward on vectorised envs (both cores), the teacher's curriculum of (scene,
density) pools, resumable from ``ppo/last.zip``. Output (``out``)::

    policy.safetensors, policy.json   the final policy (rl.baselines.common.save_baseline)
    bc/data.npz                       the expert episodes as DRL-VO observations (+ actions, returns)
    bc/policy.*                       the warm-started policy (a resumed run skips the cloning)
    ppo/last.zip                      SB3 checkpoint for --resume

**Deviations from the original, and why**

* Warm start by behaviour cloning on the privileged expert, then PPO on the default profile's budget (15 cloning
  epochs, 16,384 PPO env steps: about 10 minutes on a 2-core CPU, :class:`Config`) — the original trains PPO on
  ~2 M Gazebo steps (from a pre-trained model); the warm start makes the budget comparable with our teacher's (the
  same expert episodes). The PPO settings are the original's fine-tuning ones (lr 5e-5, batch 128) with 4 epochs
  instead of 10 (the CNN update dominates the wall time).
* The network is narrower and downsamples earlier: base width 16 instead of 64, and a stride-2 stem conv + stride-2
  max-pool (the standard ResNet stem) instead of stride 1 + stride 1 — the original runs its first stage at
  80 x 80 with 64-256 channels (~2 GMAC a sample, ~0.7 s per sample for a PPO update on our CPU). Every input cell
  is still seen (kernel ≥ stride).
* GroupNorm (8 channels a group) instead of BatchNorm: SB3 PPO evaluates the rollout's log-probabilities in eval mode
  and the update's in train mode, which BatchNorm makes disagree (a biased ratio); GroupNorm has no mode.
* PPO starts with a critic warm-up (``critic_warmup_steps`` = 4096: only the value head learns, the actor is
  frozen) and ``target_kl`` 0.02: measured on 12 seeded episodes per scene, the cloned policy reached SR 0.50 in
  the office lobby and 0.25 in the hallway at 0.1 ped/m², and 16k PPO steps straight after cloning brought it to
  0.08 and 0.00 — the cloned critic (value MSE ≈ 330 on returns of ±20) steered the first updates.
* The velocity-obstacle heading search uses 60 headings evenly spaced from the sub-goal direction instead of 60
  uniform random samples (same resolution; the reward is deterministic and exact when the sub-goal direction is
  free); angles are compared modulo 2π (the original's unwrapped comparison misses cones across ±π); the cone of a
  pedestrian closer than 3 ρ_robot is the half plane (the original's square root is NaN there, i.e. never
  blocked).
* r_g rewards per-step progress (the paper's equation; the code compares with the distance 10 control steps
  earlier). Collisions are the env's (footprints touch; the original counted lidar returns ≤ ρ_robot with a bumper
  tolerance). The robot's limits are ours (v ≤ 1 m/s instead of the Turtlebot's 0.5, |ω| ≤ 2 rad/s), the episode
  limit is the env's ``max_episode_s``.
* Value targets of the cloned episodes: the DRL-VO return of each expert step, the final step's small shaping terms
  replaced by its terminal reward (±20) since no observation follows it.
"""

from __future__ import annotations

import functools
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from pipeline.core.errors import ConfigError
from rl.baselines.common import (
    GlobalPath,
    collect_expert_episodes,
    lidar_scan,
    load_baseline,
    save_baseline,
    to_robot_frame,
    tracked_pedestrians,
    training_pairs,
)
from rl.policy import freeze_actor

NAME = "drl_vo"
MAP_CELLS = 80  # kinematic / lidar map size (cells), the original's
MAP_RES_M = 0.125  # cell size
MAP_EXTENT_M = MAP_CELLS * MAP_RES_M  # 10 m forward, ±5 m lateral
HISTORY = 10  # lidar scans in the history (1 s at 10 Hz); 2 rows each (min, mean) -> 20 rows, tiled 4x to 80
PED_SLOTS = 64  # tracks inside the map carried by the observation (nearest first)
SPEED_SCALE_MPS = 2.0  # the original's velocity scaling (MaxAbsScaler over ±2 m/s)
GOAL_SCALE_M = 2.0  # the original's sub-goal scaling (±2 m)


@dataclass
class RewardConfig:
    """DRL-VO's reward constants (the original's values)."""

    arrival: float = 20.0  # r_arrival: reward on reaching the goal, its negative on a timeout
    waypoint: float = 3.2  # r_waypoint: reward per metre of progress toward the goal
    collision: float = -20.0  # r_collision
    scan: float = -0.2  # r_scan: per metre the nearest lidar return is inside 3 ρ_robot
    angle: float = 0.6  # r_angle: weight of the heading term r_t
    angle_thresh_rad: float = math.pi / 6  # r_t = angle · (angle_thresh − |θ_vo|)
    rotation: float = -0.1  # r_rotation: per rad/s of |ω| ...
    rotation_thresh_radps: float = 1.0  # ... when |ω| exceeds this
    vo_range_m: float = 7.0  # pedestrians within this distance shape the velocity obstacles
    vo_headings: int = 60  # candidate headings of the velocity-obstacle search


@dataclass
class Config:
    """DRL-VO training options (``TrainConfig.drl_vo``); defaults are the ``default`` profile's budget.

    Measured on the 2-core CPU (alone): 200 expert episodes 48 s (24 k frames, 2 workers), cloning 28 s an epoch,
    PPO 117 env steps/s. With 3 cloning epochs and 4096 PPO steps (179 s in all) the policy was still cloning
    (action error 0.33 → 0.27 over the 3 epochs) and reached SR ≤ 0.06 on the test scenes, so the default gives
    it the ~10 minutes the other baselines get: 15 epochs and 16,384 PPO steps.
    """

    lidar_rays: int = 720  # beams over lidar_fov_deg (a multiple of 80: pooled into 80 bins)
    lidar_fov_deg: float = 180.0  # centred on the heading
    lidar_range_m: float = 30.0  # max range (also the map's normalisation)
    tracker_range_m: float = 12.0  # perfect pedestrian tracks within this distance (covers the 10 x 10 m map)
    lookahead_m: float = 2.0  # pure-pursuit sub-goal distance along the global path
    width: int = 16  # base channels of the ResNet (the original: 64); a multiple of 8
    features_dim: int = 256  # fused feature size (the original's)
    pi: list[int] = field(default_factory=lambda: [256])  # policy MLP (the original's)
    vf: list[int] = field(default_factory=lambda: [128])  # value MLP (the original's)
    bc_episodes: int | None = None  # expert episodes for the warm start (None: the teacher's bc_episodes; 0: none)
    bc_epochs: int = 15  # cloning epochs
    bc_batch: int = 128
    bc_lr: float = 1e-3
    ppo_steps: int = 16_384  # PPO env steps after the warm start (the critic warm-up included)
    critic_warmup_steps: int = 4096  # first PPO steps train only the value head (the actor is frozen)
    n_envs: int = 4  # vectorised envs
    subprocess: bool = True  # SubprocVecEnv (both cores) instead of DummyVecEnv
    ppo: dict[str, float] = field(default_factory=lambda: {"n_steps": 128, "batch_size": 128, "n_epochs": 4,
                                                           "learning_rate": 5e-5, "target_kl": 0.02})
    reward: RewardConfig = field(default_factory=RewardConfig)

    def validate(self) -> None:
        from rl.teacher import ppo_kwargs

        if self.lidar_rays < MAP_CELLS or self.lidar_rays % MAP_CELLS:
            raise ConfigError(f"drl_vo.lidar_rays: expected a positive multiple of {MAP_CELLS} (pooled into "
                              f"{MAP_CELLS} bins), got {self.lidar_rays}")
        if not 0.0 < self.lidar_fov_deg <= 360.0:
            raise ConfigError(f"drl_vo.lidar_fov_deg: expected 0 < fov <= 360, got {self.lidar_fov_deg}")
        for key in ("lidar_range_m", "tracker_range_m", "lookahead_m", "bc_lr"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"drl_vo.{key}: expected > 0, got {getattr(self, key)}")
        if self.width < 8 or self.width % 8:
            raise ConfigError(f"drl_vo.width: expected a multiple of 8 (GroupNorm of 8 channels), got {self.width}")
        if self.features_dim < 1 or not self.pi or not self.vf or min(*self.pi, *self.vf) < 1:
            raise ConfigError(f"drl_vo: expected features_dim >= 1 and non-empty pi / vf layer sizes >= 1, got "
                              f"{self.features_dim}, {self.pi}, {self.vf}")
        if self.bc_episodes is not None and self.bc_episodes < 0:
            raise ConfigError(f"drl_vo.bc_episodes: expected >= 0 or null (the teacher's), got {self.bc_episodes}")
        for key in ("bc_epochs", "bc_batch", "n_envs"):
            if getattr(self, key) < 1:
                raise ConfigError(f"drl_vo.{key}: expected an integer >= 1, got {getattr(self, key)}")
        if self.ppo_steps < 0 or self.critic_warmup_steps < 0:
            raise ConfigError(f"drl_vo.ppo_steps / critic_warmup_steps: expected >= 0, got {self.ppo_steps} / "
                              f"{self.critic_warmup_steps}")
        if self.reward.vo_headings < 2 or self.reward.vo_range_m <= 0:
            raise ConfigError(f"drl_vo.reward: expected vo_headings >= 2 and vo_range_m > 0, got "
                              f"{self.reward.vo_headings}, {self.reward.vo_range_m}")
        ppo_kwargs(self.ppo)  # unknown keys -> ConfigError naming them

    def sensors(self) -> dict[str, float]:
        """The observer's options (saved in the checkpoint: the driver observes exactly as in training)."""
        return {"lidar_rays": self.lidar_rays, "lidar_fov_deg": self.lidar_fov_deg,
                "lidar_range_m": self.lidar_range_m, "tracker_range_m": self.tracker_range_m,
                "lookahead_m": self.lookahead_m}

    def net(self) -> dict[str, Any]:
        """What :func:`build_policy` builds (``policy.json``'s ``net``)."""
        return {"width": self.width, "features_dim": self.features_dim, "pi": list(self.pi), "vf": list(self.vf),
                "lidar_range_m": self.lidar_range_m}


def inputs(cfg) -> list[Path]:
    """DRL-VO needs nothing but the simulator."""
    return []


# ------------------------------------------------------------------------------------------------------ observing
def observation_space(lidar_range_m: float) -> gym.spaces.Dict:
    """``peds`` K x 5 [x, y, vx, vy, present] (robot frame, m, m/s), ``scan`` 20 x 80 (m; rows 2n / 2n+1: min /
    mean over each 9-beam bin of scan n, oldest first, bins right to left), ``goal`` 2 (sub-goal, robot frame, m)."""
    big = np.float32(1e4)
    return gym.spaces.Dict({
        "peds": gym.spaces.Box(-big, big, (PED_SLOTS, 5), np.float32),
        "scan": gym.spaces.Box(0.0, np.float32(lidar_range_m), (2 * HISTORY, MAP_CELLS), np.float32),
        "goal": gym.spaces.Box(-big, big, (2,), np.float32),
    })


def pool_scans(scans: np.ndarray) -> np.ndarray:
    """``H x R`` ranges → ``2H x 80``: row 2n the minimum, row 2n+1 the mean of each of the 80 bins of scan n."""
    h, r = scans.shape
    bins = scans.reshape(h, MAP_CELLS, r // MAP_CELLS)
    return np.stack([bins.min(-1), bins.mean(-1)], 1).reshape(2 * h, MAP_CELLS).astype(np.float32)


def kinematic_map(peds: torch.Tensor) -> torch.Tensor:
    """``B x K x 5`` tracks [x, y, vx, vy, present] (robot frame) → ``B x 2 x 80 x 80`` kinematic map: (vx, vy) of
    each present track with 0 ≤ x ≤ 10 m and |y| ≤ 5 m in cell (⌊x / 0.125⌋, ⌊(5 − y) / 0.125⌋) (row 0 nearest,
    column 0 leftmost; the far edges fall into the last cell). Two tracks in one cell add up (bodies cannot share a
    12.5 cm cell)."""
    b, k, _ = peds.shape
    x, y = peds[..., 0], peds[..., 1]
    inside = (peds[..., 4] > 0.5) & (x >= 0) & (x <= MAP_EXTENT_M) & (y.abs() <= MAP_EXTENT_M / 2)
    row = torch.clamp(torch.floor(x / MAP_RES_M), 0, MAP_CELLS - 1).long()
    col = torch.clamp(torch.floor((MAP_EXTENT_M / 2 - y) / MAP_RES_M), 0, MAP_CELLS - 1).long()
    vel = (peds[..., 2:4] * inside.unsqueeze(-1)).transpose(1, 2)  # B x 2 x K
    out = peds.new_zeros(b, 2, MAP_CELLS * MAP_CELLS)
    out.scatter_add_(2, (row * MAP_CELLS + col).unsqueeze(1).expand(b, 2, k), vel)
    return out.view(b, 2, MAP_CELLS, MAP_CELLS)


class Observer:
    """DRL-VO's observation of a :class:`sim.env.CrowdNavEnv` (module docstring): keeps the lidar history and the
    global path of one episode. ``reset(env)`` at the start of each episode, then ``observer(env, target)`` each
    step (``target``: a world-frame waypoint replacing the goal)."""

    def __init__(self, lidar_rays: int, lidar_fov_deg: float, lidar_range_m: float, tracker_range_m: float,
                 lookahead_m: float) -> None:
        self.rays, self.fov_rad, self.range_m = int(lidar_rays), math.radians(lidar_fov_deg), float(lidar_range_m)
        self.tracker_range_m = float(tracker_range_m)
        self.path = GlobalPath(lookahead_m)
        self.space = observation_space(self.range_m)
        self.scans: np.ndarray | None = None  # HISTORY x rays, oldest first
        self.tracks = np.zeros((0, 5), np.float32)  # the last step's tracks (robot frame), for the reward
        self.last: dict[str, np.ndarray] = {}

    def reset(self, env, obs: dict | None = None) -> None:
        self.path.reset(env)
        self.scans = None
        self.last = {}

    def __call__(self, env, obs: dict | None = None, target: np.ndarray | None = None) -> dict[str, np.ndarray]:
        scan = lidar_scan(env, self.rays, self.fov_rad, self.range_m)
        if self.scans is None:  # a new episode: the history starts as copies of the first scan
            self.scans = np.repeat(scan[None], HISTORY, 0)
        else:
            self.scans = np.concatenate([self.scans[1:], scan[None]])
        self.tracks = tracked_pedestrians(env, self.tracker_range_m)
        t = self.tracks
        in_map = (t[:, 0] >= 0) & (t[:, 0] <= MAP_EXTENT_M) & (np.abs(t[:, 1]) <= MAP_EXTENT_M / 2)
        kept = t[in_map][:PED_SLOTS]
        peds = np.zeros((PED_SLOTS, 5), np.float32)
        peds[:len(kept), :4] = kept[:, :4]
        peds[:len(kept), 4] = 1.0
        goal = to_robot_frame(env, self.path.subgoal(env, target))
        self.last = {"peds": peds, "scan": pool_scans(self.scans), "goal": goal}
        return self.last

    def reward_terms(self, env, cfg: RewardConfig, d_goal_prev: float, outcome: str | None) -> dict[str, float]:
        """DRL-VO's reward of the step that led to ``env``'s state (call after observing that state)."""
        heading = vo_heading(self.last["goal"], self.tracks, float(env.robot_v[0]), env.cfg.robot.radius_m,
                             cfg.vo_range_m, cfg.vo_headings)
        return reward_terms(cfg, outcome, env.d_goal, d_goal_prev, float(self.scans[-1].min()),
                            float(env.robot_v[1]), heading, env.cfg.robot.radius_m)


def _wrap(a: np.ndarray | float) -> np.ndarray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def vo_heading(goal_rf: np.ndarray, tracks: np.ndarray, speed_mps: float, robot_radius_m: float, range_m: float,
               n_headings: int) -> float:
    """DRL-VO's desired heading θ_vo (robot frame, rad, in [−π, π)): of ``n_headings`` headings evenly spaced from
    the sub-goal direction, the one closest to it whose velocity (``speed_mps`` along it) relative to each
    pedestrian's lies outside that pedestrian's collision cone (half-angle asin(3 ρ_robot / d) around its
    direction; the half plane when d ≤ 3 ρ_robot), for the tracks (``M x ≥4`` [x, y, vx, vy], robot frame) within
    ``range_m``. π/2 when every heading is blocked; the sub-goal direction when no track is within range."""
    pre = math.atan2(float(goal_rf[1]), float(goal_rf[0]))
    t = np.asarray(tracks, np.float64)
    t = t[np.hypot(t[:, 0], t[:, 1]) <= range_m] if len(t) else t
    if not len(t):
        return float(_wrap(pre))
    theta = _wrap(pre + (np.arange(n_headings) - n_headings // 2) * (2 * np.pi / n_headings))  # N, theta[N/2]=pre
    dist = np.hypot(t[:, 0], t[:, 1])
    half = np.arcsin(np.minimum(1.0, 3 * robot_radius_m / np.maximum(dist, 1e-9)))  # M
    rel = np.arctan2(speed_mps * np.sin(theta)[:, None] - t[None, :, 3],
                     speed_mps * np.cos(theta)[:, None] - t[None, :, 2])  # N x M: robot velocity − pedestrian's
    blocked = (np.abs(_wrap(rel - np.arctan2(t[:, 1], t[:, 0])[None])) <= half[None]).any(1)
    if blocked.all():
        return math.pi / 2
    free = theta[~blocked]
    return float(free[np.argmin(np.abs(_wrap(free - pre)))])


def reward_terms(cfg: RewardConfig, outcome: str | None, d_goal: float, d_goal_prev: float, scan_min_m: float,
                 omega_radps: float, heading_rad: float, robot_radius_m: float) -> dict[str, float]:
    """DRL-VO's reward of one step: ``{"goal", "collision", "rotation", "heading", "total"}`` (module docstring).
    ``outcome``: the env's (None while the episode runs, success / collision_* / timeout)."""
    if outcome == "success":
        r_g = cfg.arrival
    elif outcome == "timeout":
        r_g = -cfg.arrival
    else:
        r_g = cfg.waypoint * (d_goal_prev - d_goal)
    near = 3 * robot_radius_m
    if outcome is not None and outcome.startswith("collision"):
        r_c = cfg.collision
    else:
        r_c = cfg.scan * (near - scan_min_m) if scan_min_m < near else 0.0
    r_w = cfg.rotation * abs(omega_radps) if abs(omega_radps) > cfg.rotation_thresh_radps else 0.0
    r_t = cfg.angle * (cfg.angle_thresh_rad - abs(heading_rad))
    t = {"goal": float(r_g), "collision": float(r_c), "rotation": float(r_w), "heading": float(r_t)}
    t["total"] = sum(t.values())
    return t


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
    from rl.teacher import _discounted

    out = np.zeros(len(data["done"]), np.float32)
    ends = np.flatnonzero(data["done"]) + 1
    for s, e in zip(np.r_[0, ends[:-1]], ends, strict=True):
        last = arrival if data["success"][e - 1] else -arrival
        out[s:e] = _discounted([*data["prev_reward"][s + 1:e].tolist(), last], gamma)
    return out


# -------------------------------------------------------------------------------------------------------- network
def _norm(c: int) -> nn.GroupNorm:
    return nn.GroupNorm(c // 8, c)


def _conv(cin: int, cout: int, k: int, stride: int = 1, bias: bool = False) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, k, stride, k // 2, bias=bias)


class _Bottleneck(nn.Module):
    """ResNet V1.5 bottleneck (1x1 → 3x3 with the stride → 1x1, expansion 2 as DRL-VO's) with a projected shortcut
    when the shape changes."""

    def __init__(self, cin: int, planes: int, stride: int = 1) -> None:
        super().__init__()
        cout = 2 * planes
        self.branch = nn.Sequential(_conv(cin, planes, 1), _norm(planes), nn.ReLU(),
                                    _conv(planes, planes, 3, stride), _norm(planes), nn.ReLU(),
                                    _conv(planes, cout, 1), _norm(cout))
        self.shortcut = (nn.Sequential(_conv(cin, cout, 1, stride), _norm(cout)) if stride != 1 or cin != cout
                         else nn.Identity())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.branch(x) + self.shortcut(x))


def _block(c: int, mid: int) -> nn.Sequential:
    """DRL-VO's 1x1 → 3x3 → 1x1 residual branch (``conv2_2`` / ``conv3_2``)."""
    return nn.Sequential(_conv(c, mid, 1, bias=True), _norm(mid), nn.ReLU(), _conv(mid, mid, 3, bias=True),
                         _norm(mid), nn.ReLU(), _conv(mid, c, 1, bias=True), _norm(c))


class DRLVOExtractor(BaseFeaturesExtractor):
    """DRL-VO's early-fusion ResNet over [lidar map, kinematic map] (3 x 80 x 80) + the sub-goal → ``features_dim``.

    Shapes with base width w: 3 x 80² → stem (conv s2 + max-pool s2) w x 20² → 2 bottlenecks 2w x 20² → bottleneck
    s2 + block (+ shortcut s2 from the first stage) 4w x 10² → bottleneck s2 + block (+ shortcut s4 from the stem)
    8w x 5² → average pool 8w ⊕ sub-goal 2 → FC ``features_dim`` + ReLU.
    """

    def __init__(self, observation_space: gym.spaces.Dict, width: int = 16, features_dim: int = 256) -> None:
        super().__init__(observation_space, features_dim)
        w = width
        self.range_m = float(np.max(observation_space["scan"].high))
        self.stem = nn.Sequential(_conv(3, w, 3, 2), _norm(w), nn.ReLU(), nn.MaxPool2d(3, 2, 1))
        self.layer1 = nn.Sequential(_Bottleneck(w, w), _Bottleneck(2 * w, w))
        self.layer2 = _Bottleneck(2 * w, 2 * w, 2)
        self.block2, self.short2 = _block(4 * w, 2 * w), nn.Sequential(_conv(2 * w, 4 * w, 1, 2, True), _norm(4 * w))
        self.layer3 = _Bottleneck(4 * w, 4 * w, 2)
        self.block3, self.short3 = _block(8 * w, 4 * w), nn.Sequential(_conv(w, 8 * w, 1, 4, True), _norm(8 * w))
        self.fc = nn.Sequential(nn.Linear(8 * w + 2, features_dim), nn.ReLU())
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.Linear):
                nn.init.xavier_normal_(m.weight)
        for m in self.modules():  # residual branches start as zero (identity blocks), as the original
            if isinstance(m, _Bottleneck):
                nn.init.zeros_(m.branch[-1].weight)

    def maps(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """The network's input image ``B x 3 x 80 x 80``: [lidar map, vx, vy], scaled to about [−1, 1]."""
        scan = 2.0 * obs["scan"] / self.range_m - 1.0  # B x 20 x 80
        scan = scan.unsqueeze(1).repeat(1, 1, MAP_CELLS // scan.shape[1], 1)
        return torch.cat([scan, kinematic_map(obs["peds"]) / SPEED_SCALE_MPS], 1)

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        x = self.stem(self.maps(obs))
        s3 = self.short3(x)
        x = self.layer1(x)
        s2 = self.short2(x)
        x = torch.relu(self.block2(self.layer2(x)) + s2)
        x = torch.relu(self.block3(self.layer3(x)) + s3)
        return self.fc(torch.cat([x.mean((2, 3)), obs["goal"] / GOAL_SCALE_M], 1))


def policy_kwargs(net: dict[str, Any]) -> dict[str, Any]:
    """SB3 ``policy_kwargs`` of the network described by ``net`` (:meth:`Config.net`)."""
    return {"features_extractor_class": DRLVOExtractor,
            "features_extractor_kwargs": {"width": int(net["width"]), "features_dim": int(net["features_dim"])},
            "net_arch": {"pi": [int(n) for n in net["pi"]], "vf": [int(n) for n in net["vf"]]},
            "share_features_extractor": True}


def build_policy(net: dict[str, Any]) -> ActorCriticPolicy:
    """A fresh actor-critic (random weights) over the DRL-VO observation and the normalised (v, ω) box."""
    return ActorCriticPolicy(observation_space(float(net["lidar_range_m"])), gym.spaces.Box(-1.0, 1.0, (2,), np.float32),
                             lambda _: 0.0, **policy_kwargs(net))


# ------------------------------------------------------------------------------------------------------- training
def _clone(policy: ActorCriticPolicy, data: dict[str, np.ndarray], epochs: int, batch: int, lr: float, seed: int,
           progress: bool) -> list[dict[str, float]]:
    """Behaviour cloning: Gaussian negative log-likelihood of the expert's actions (mean and log-std) + 0.5 · MSE of
    the value on the DRL-VO returns divided by their variance (returns span ±20 and more: unscaled, the value's
    gradient would drown the policy's in the shared extractor). One row per epoch: ``{"epoch", "nll",
    "action_mae", "value_loss"}`` (value_loss: the unscaled MSE)."""
    from tqdm import tqdm

    keys = tuple(policy.observation_space.spaces)
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
            obs = {k: torch.as_tensor(data[k][idx]) for k in keys}
            act = torch.as_tensor(data["action"][idx], dtype=torch.float32)
            latent_pi, latent_vf = policy.mlp_extractor(policy.extract_features(obs))
            mean = policy.action_net(latent_pi)
            nll = -policy.action_dist.proba_distribution(mean, policy.log_std).log_prob(act).mean()
            v_loss = nn.functional.mse_loss(policy.value_net(latent_vf).flatten(), torch.as_tensor(data["return"][idx]))
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
    from rl.teacher import SceneMixEnv

    return DRLVOEnv(SceneMixEnv(sim_cfg, pairs, obs_mode="privileged", action_type="continuous"), sensors, reward)


def _log_callback(log):
    """Logs the mean episode return, length and success rate of the last episodes after every rollout."""
    from stable_baselines3.common.callbacks import BaseCallback

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


def train(cfg, out: Path, log) -> dict[str, Any]:
    """Trains DRL-VO into ``out`` (module docstring: warm start, then PPO; resumable) and writes the final
    checkpoint. Returns the summary with its ``budget``."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecMonitor

    from rl.stage import _checkpoint_callback, _progress_callback, atomic_save_npz
    from rl.teacher import curriculum_callback, ppo_kwargs

    c: Config = cfg.drl_vo
    c.validate()
    out = Path(out)
    pairs = training_pairs(cfg)
    sensors, net = c.sensors(), c.net()
    ppo = ppo_kwargs(c.ppo)
    episodes = cfg.teacher.bc_episodes if c.bc_episodes is None else c.bc_episodes
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    wall: dict[str, float] = {}
    summary: dict[str, Any] = {}
    bc_dir = out / "bc"
    frames = 0
    if episodes and (bc_dir / "policy.json").is_file():  # resuming: the warm start is done
        policy, desc = load_baseline(bc_dir, NAME, build_policy)
        summary["bc"] = desc["bc"]
        frames = int(desc["bc"]["frames"])
    else:
        torch.manual_seed(cfg.seed)
        policy = build_policy(net)
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
    ppo_steps = 0
    if c.ppo_steps > 0:
        sim_cfg = cfg.sim
        fns = [functools.partial(_make_env, sim_cfg, pairs, sensors, c.reward)] * c.n_envs
        venv = SubprocVecEnv(fns, start_method="fork") if c.subprocess and c.n_envs > 1 else DummyVecEnv(fns)
        venv = VecMonitor(venv, info_keywords=("is_success",))
        venv.seed(cfg.seed + 1)
        last = out / "ppo" / "last.zip"
        if last.exists():
            model = PPO.load(last, env=venv, device="cpu")
        else:
            model = PPO("MultiInputPolicy", venv, policy_kwargs=policy_kwargs(net), seed=cfg.seed, device="cpu",
                        verbose=0, **ppo)
            model.policy.load_state_dict(policy.state_dict())
        done = model.num_timesteps
        t0 = time.perf_counter()
        cb = [curriculum_callback(cfg.teacher.curriculum, c.ppo_steps), _checkpoint_callback(out / "ppo", model, 5_000),
              _progress_callback(c.ppo_steps, "drl_vo PPO", cfg.progress), _log_callback(log)]
        warm = min(c.critic_warmup_steps, c.ppo_steps)
        if done < warm:  # the cloned critic is poor: fit it on-policy before the actor moves (measured below)
            frozen = freeze_actor(model.policy)
            model.learn(warm - done, callback=cb, reset_num_timesteps=False)
            for p in frozen:
                p.requires_grad_(True)
        model.learn(max(0, c.ppo_steps - model.num_timesteps), callback=cb, reset_num_timesteps=False)
        wall["ppo_s"] = round(time.perf_counter() - t0, 1)
        summary["ppo_steps_per_s"] = round((model.num_timesteps - done) / max(wall["ppo_s"], 1e-9), 1)
        ppo_steps = int(model.num_timesteps)
        last.parent.mkdir(parents=True, exist_ok=True)
        model.save(last)
        venv.close()
        policy = model.policy
        policy.set_training_mode(False)
    budget = {"expert_episodes": episodes, "expert_frames": frames, "bc_epochs": c.bc_epochs if episodes else 0,
              "ppo_env_steps": ppo_steps, "wall_s": wall}
    robot = cfg.sim.robot
    save_baseline(out, NAME, policy, net, describe_inputs(policy), budget, observer=sensors,
                  robot={"v_max_mps": robot.v_max_mps, "omega_max_radps": robot.omega_max_radps},
                  reward=asdict(c.reward))
    summary["budget"] = budget
    return summary


def describe_inputs(policy: ActorCriticPolicy) -> dict[str, Any]:
    """A description of the policy's inputs and actions (``policy.json``'s ``observation_space``)."""
    from rl.policy import space_to_json

    return {**space_to_json(policy.observation_space),
            "actions": "Box([-1, 1]^2): v = (a0 + 1) / 2 · v_max, ω = a1 · ω_max"}


# --------------------------------------------------------------------------------------------------------- driving
class Driver:
    """Drives with a trained DRL-VO checkpoint (deterministic: the Gaussian's mean)."""

    def __init__(self, ckpt: Path) -> None:
        self.policy, desc = load_baseline(Path(ckpt), NAME, build_policy)
        try:
            self.observer = Observer(**desc["observer"])
            self.v_max, self.w_max = float(desc["robot"]["v_max_mps"]), float(desc["robot"]["omega_max_radps"])
        except (KeyError, TypeError) as e:
            from pipeline.core.errors import CorruptArtifactError

            raise CorruptArtifactError(f"{Path(ckpt) / 'policy.json'}: not a drl_vo description "
                                       f"({type(e).__name__}: {e})") from None
        self.last: dict[str, np.ndarray] = {}

    def reset(self, env, obs: dict | None = None) -> None:
        self.observer.reset(env)
        self.last = {}

    @torch.no_grad()
    def act(self, env, obs: dict | None = None, waypoint: np.ndarray | None = None):
        """The env action of the policy's (v, ω) toward ``waypoint`` (None: the goal)."""
        self.last = self.observer(env, target=waypoint)
        a, _ = self.policy.predict(self.last, deterministic=True)
        a = np.clip(np.asarray(a, np.float64).reshape(2), -1.0, 1.0)
        return env.encode_command((a[0] + 1.0) / 2.0 * self.v_max, a[1] * self.w_max)

    def bev_panel(self) -> np.ndarray | None:
        """Speed (m/s) in each cell of the last kinematic map (80 x 80, row 0 nearest), None before a step."""
        if not self.last:
            return None
        m = kinematic_map(torch.as_tensor(self.last["peds"])[None])[0].numpy()
        return np.hypot(m[0], m[1])

