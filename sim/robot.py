"""Diff-drive robot: unicycle kinematics, limits and the discrete action grid."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class RobotConfig:
    """The robot body and its limits (Clearpath Dingo-like)."""

    radius_m: float = 0.3  # footprint disc radius, ρ_robot
    v_max_mps: float = 1.0  # forward speed limit (no reversing): v ∈ [0, v_max]
    omega_max_radps: float = 2.0  # yaw-rate limit: ω ∈ [−ω_max, ω_max]
    n_speeds: int = 5  # discrete action grid: speeds ...
    n_rotations: int = 21  # ... × yaw rates (5 × 21 as in the authors' code)

    def validate(self) -> None:
        from pipeline.core.errors import ConfigError

        for k in ("radius_m", "v_max_mps", "omega_max_radps"):
            if getattr(self, k) <= 0:
                raise ConfigError(f"robot.{k}: expected > 0, got {getattr(self, k)}")
        if self.n_speeds < 2 or self.n_rotations < 3:
            raise ConfigError(f"robot action grid: expected n_speeds >= 2 and n_rotations >= 3, got "
                              f"{self.n_speeds} x {self.n_rotations}")


def action_grid(cfg: RobotConfig) -> np.ndarray:
    """``(n_speeds·n_rotations) x 2`` table of [v, ω]: speeds evenly from 0 to v_max, yaw rates evenly in ±ω_max.

    Index ``k = i_speed · n_rotations + i_rotation``.
    """
    v = np.linspace(0.0, cfg.v_max_mps, cfg.n_speeds)
    w = np.linspace(-cfg.omega_max_radps, cfg.omega_max_radps, cfg.n_rotations)
    vv, ww = np.meshgrid(v, w, indexing="ij")
    return np.stack([vv.ravel(), ww.ravel()], -1)


def unicycle_step(x: float, y: float, yaw: float, v: float, omega: float, dt: float) -> tuple[float, float, float]:
    """Exact integration of constant (v, ω) over ``dt`` (arc of a circle; straight line when ω = 0)."""
    if abs(omega) < 1e-6:
        return x + v * dt * math.cos(yaw), y + v * dt * math.sin(yaw), yaw
    r = v / omega
    nyaw = yaw + omega * dt
    return x + r * (math.sin(nyaw) - math.sin(yaw)), y - r * (math.cos(nyaw) - math.cos(yaw)), \
        (nyaw + math.pi) % (2 * math.pi) - math.pi
