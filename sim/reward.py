"""The paper's reward (Eq. 9–10), term by term.

``r = r_nav + r_ω`` with::

    r_nav = +20                     if d_g ≤ goal radius           (success)
          = −20                     elif d_o ≤ ρ_robot              (collision)
          = 0.5 (d_o − 0.9)         elif ρ_robot < d_o < 0.9        (too close)
          = 3.2 (d_g^{t−1} − d_g^t) otherwise                      (progress)
    r_ω   = −0.1 |ω|  if |ω| > 1.0, else 0

``d_o`` is the distance from the robot centre to the nearest pedestrian body surface or obstacle surface, so
``d_o ≤ ρ_robot`` means the footprints touch. The paper's goal test is ``d_g ≤ ρ_robot``; the goal radius is a
config value that defaults to ρ_robot.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class RewardConfig:
    """Weights of the paper's reward; defaults are the paper's values."""

    success: float = 20.0  # terminal reward on reaching the goal
    collision: float = -20.0  # terminal reward on a collision
    near_weight: float = 0.5  # slope of the proximity penalty
    near_distance_m: float = 0.9  # d_o below which the proximity penalty applies
    progress_weight: float = 3.2  # reward per metre of progress toward the goal
    spin_weight: float = 0.1  # smoothing penalty per rad/s ...
    spin_threshold_radps: float = 1.0  # ... when |ω| exceeds this


def reward_terms(cfg: RewardConfig, d_goal: float, d_goal_prev: float, d_o: float, omega: float,
                 robot_radius: float, goal_radius: float) -> dict[str, float]:
    """Each term of the reward for one step (exactly one of the four r_nav cases is non-zero).

    Returns:
        ``{"success", "collision", "near", "progress", "spin", "total"}``.
    """
    t = {"success": 0.0, "collision": 0.0, "near": 0.0, "progress": 0.0, "spin": 0.0}
    if d_goal <= goal_radius:
        t["success"] = cfg.success
    elif d_o <= robot_radius:
        t["collision"] = cfg.collision
    elif d_o < cfg.near_distance_m:
        t["near"] = cfg.near_weight * (d_o - cfg.near_distance_m)
    else:
        t["progress"] = cfg.progress_weight * (d_goal_prev - d_goal)
    if abs(omega) > cfg.spin_threshold_radps:
        t["spin"] = -cfg.spin_weight * abs(omega)
    t["total"] = sum(t.values())
    return t
