"""SARL*-OM's reward R (package docstring): CrowdNav's terms with Samsani & Muhammad's danger zones."""

from __future__ import annotations

import math

import numpy as np

from rl.baselines.sarl_om.configuration import Config
from rl.baselines.sarl_om.observation import Scene
from sim.geometry import wrap_angle


def danger_depth(rel: np.ndarray, hvel: np.ndarray, hr: np.ndarray, robot_radius: float, oc: Config) -> np.ndarray:
    """How deep the robot is in each human's danger zone, in [0, 1] (0 = outside).

    Args:
        rel: ``... x M x 2`` robot position minus human position (any common frame).
        hvel: ``M x 2`` human velocities (same frame); ``hr``: ``M`` human radii.
    """
    speed = np.hypot(hvel[:, 0], hvel[:, 1])
    contact = hr + robot_radius
    reach = contact + oc.dz_margin_m + oc.dz_time_s * speed  # zone radius
    half = 0.5 * (11 * math.pi / 6 * np.exp(-1.4 * speed) + math.pi / 6)  # half opening (π at rest)
    dist = np.hypot(rel[..., 0], rel[..., 1])
    off = np.abs(wrap_angle(np.arctan2(rel[..., 1], rel[..., 0]) - np.arctan2(hvel[:, 1], hvel[:, 0])))
    inside = (dist < reach) & ((off <= half) | (half >= math.pi - 1e-9))
    return np.where(inside, np.clip((reach - dist) / (reach - contact), 0.0, 1.0), 0.0)


def reward(sc: Scene, pos: np.ndarray, hpos: np.ndarray, d_goal_prev: float, dt: float,
           oc: Config) -> tuple[np.ndarray, np.ndarray]:
    """R of arriving at robot positions ``pos`` (B x 2) with the humans at ``hpos`` (M x 2): (reward B, terminal
    B). Terms in the package docstring."""
    d_goal = np.hypot(*(sc.goal[None, :] - pos).T)
    r = oc.progress_weight * (d_goal_prev - d_goal)
    collide = np.zeros(len(pos), bool)
    if len(sc.hits):
        clear = np.sqrt(((pos[:, None, :] - sc.hits[None]) ** 2).sum(-1).min(1))
        collide |= clear <= sc.radius
    if len(hpos):
        rel = pos[:, None, :] - hpos[None]  # B x M x 2
        gap = (np.hypot(rel[..., 0], rel[..., 1]) - sc.humans[None, :, 4] - sc.radius).min(1)
        collide |= gap <= 0.0
        r = r + np.where(gap < oc.discomfort_m, (gap - oc.discomfort_m) * oc.discomfort_factor * dt, 0.0)
        r = r - oc.dz_weight * dt * danger_depth(rel, sc.humans[:, 2:4], sc.humans[:, 4], sc.radius, oc).sum(1)
    reach = (d_goal <= sc.goal_radius) & ~collide
    r = np.where(collide, oc.collision_penalty, np.where(reach, oc.success_reward, r))
    return r, collide | reach
