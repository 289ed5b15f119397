"""What DRL-VO observes (package docstring): the lidar history, the pedestrian tracks of the kinematic map and the
sub-goal, built from the env each step."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import torch

from rl.baselines.common import lidar_scan, to_robot_frame, tracked_pedestrians
from rl.baselines.drl_vo.configuration import (
    HISTORY,
    MAP_CELLS,
    MAP_EXTENT_M,
    MAP_RES_M,
    PED_SLOTS,
    RewardConfig,
)
from rl.baselines.drl_vo.rewards import reward_terms, vo_heading
from sim.planners.global_path import GlobalPath


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
    """DRL-VO's observation of a :class:`sim.env.CrowdNavEnv` (package docstring): keeps the lidar history and the
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
