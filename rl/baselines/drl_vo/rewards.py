"""DRL-VO's reward (package docstring): its terms and the velocity-obstacle heading θ_vo."""

from __future__ import annotations

import math

import numpy as np

from rl.baselines.drl_vo.configuration import RewardConfig
from sim.geometry import wrap_angle


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
        return float(wrap_angle(pre))
    theta = wrap_angle(pre + (np.arange(n_headings) - n_headings // 2) * (2 * np.pi / n_headings))  # N, theta[N/2]=pre
    dist = np.hypot(t[:, 0], t[:, 1])
    half = np.arcsin(np.minimum(1.0, 3 * robot_radius_m / np.maximum(dist, 1e-9)))  # M
    rel = np.arctan2(speed_mps * np.sin(theta)[:, None] - t[None, :, 3],
                     speed_mps * np.cos(theta)[:, None] - t[None, :, 2])  # N x M: robot velocity − pedestrian's
    blocked = (np.abs(wrap_angle(rel - np.arctan2(t[:, 1], t[:, 0])[None])) <= half[None]).any(1)
    if blocked.all():
        return math.pi / 2
    free = theta[~blocked]
    return float(free[np.argmin(np.abs(wrap_angle(free - pre)))])


def reward_terms(cfg: RewardConfig, outcome: str | None, d_goal: float, d_goal_prev: float, scan_min_m: float,
                 omega_radps: float, heading_rad: float, robot_radius_m: float) -> dict[str, float]:
    """DRL-VO's reward of one step: ``{"goal", "collision", "rotation", "heading", "total"}`` (package docstring).
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
