"""DRL-VO's training options (``TrainConfig.drl_vo``), its reward constants and the sizes of its observation."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from pipeline.core.errors import ConfigError
from rl.baselines import check_curve_budgets
from rl.teacher import ppo_kwargs

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

    The default gives it the ~10 minutes the other baselines get: 15 cloning epochs and 16,384 PPO steps (a smaller
    budget was measured too small: docs/notes/2026-11-drl-vo-small-budget.md).
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
    # the learning curve: the policy is also saved after the warm start and at these PPO step counts (curve/), and
    # ``train`` runs the acceptance episodes on each (metrics.json "learning_curve", learning_curve.png)
    curve_steps: list[int] = field(default_factory=list)
    n_envs: int = 4  # vectorised envs
    subprocess: bool = True  # rl.vec_env.BatchedSubprocVecEnv (a worker per core) instead of DummyVecEnv
    ppo: dict[str, float] = field(default_factory=lambda: {"n_steps": 128, "batch_size": 128, "n_epochs": 4,
                                                           "learning_rate": 5e-5, "target_kl": 0.02})
    reward: RewardConfig = field(default_factory=RewardConfig)

    def validate(self) -> None:
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
        check_curve_budgets(self.curve_steps, self.ppo_steps, "drl_vo.curve_steps", "PPO step counts", "ppo_steps")
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
