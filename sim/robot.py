"""Diff-drive robot: unicycle kinematics, limits and the discrete action grid."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from pipeline.core.errors import ConfigError


@dataclass
class RobotConfig:
    """The robot body and its limits (Clearpath Dingo-like)."""

    radius_m: float = 0.3  # footprint disc radius, ρ_robot
    v_max_mps: float = 1.0  # forward speed limit (no reversing): v ∈ [0, v_max]
    omega_max_radps: float = 2.0  # yaw-rate limit: ω ∈ [−ω_max, ω_max]
    n_speeds: int = 5  # discrete action grid: speeds ...
    n_rotations: int = 21  # ... × yaw rates (5 × 21 as in the authors' code)

    def validate(self) -> None:
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


@dataclass(frozen=True)
class ActionCodec:
    """Physical commands (v m/s, ω rad/s) ↔ actions of an env's action space.

    ``continuous``: Box([-1, 1]²), v = (a₀ + 1)/2 · v_max and ω = a₁ · ω_max; ``discrete``: an index into
    :func:`action_grid`. The env returns its codec in ``info["action_codec"]`` at reset, so that a driver turns
    its command into an action without reading the env.
    """

    action_type: str  # "continuous" | "discrete"
    robot: RobotConfig

    @functools.cached_property
    def grid(self) -> np.ndarray:
        """The discrete action table (:func:`action_grid`)."""
        return action_grid(self.robot)

    def decode(self, action) -> tuple[float, float]:
        """Physical (v m/s, ω rad/s) of an action (clipped to the limits)."""
        r = self.robot
        if self.action_type == "discrete":
            v, w = self.grid[int(action)]
            return float(v), float(w)
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(2), -1.0, 1.0)
        return float((a[0] + 1.0) / 2.0 * r.v_max_mps), float(a[1] * r.omega_max_radps)

    def encode(self, v: float, omega: float):
        """The action closest to the physical command (v, ω)."""
        r = self.robot
        v = float(np.clip(v, 0.0, r.v_max_mps))
        omega = float(np.clip(omega, -r.omega_max_radps, r.omega_max_radps))
        if self.action_type == "discrete":
            g = self.grid
            d = ((g[:, 0] - v) / r.v_max_mps) ** 2 + ((g[:, 1] - omega) / r.omega_max_radps) ** 2
            return int(np.argmin(d))
        return np.array([2.0 * v / r.v_max_mps - 1.0, omega / r.omega_max_radps], dtype=np.float32)


def unicycle_step(x: float, y: float, yaw: float, v: float, omega: float, dt: float) -> tuple[float, float, float]:
    """Exact integration of constant (v, ω) over ``dt`` (arc of a circle; straight line when ω = 0)."""
    if abs(omega) < 1e-6:
        return x + v * dt * math.cos(yaw), y + v * dt * math.sin(yaw), yaw
    r = v / omega
    nyaw = yaw + omega * dt
    return x + r * (math.sin(nyaw) - math.sin(yaw)), y - r * (math.cos(nyaw) - math.cos(yaw)), \
        (nyaw + math.pi) % (2 * math.pi) - math.pi
