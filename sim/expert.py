"""The privileged expert: sampling-based velocity selection with constant-velocity crowd prediction.

It sees what no deployed robot sees — the true positions and velocities of every pedestrian and the static map
— and drives the first recordings and serves as the DAgger label source and an upper reference in the
benchmark. Each control step it

1. rolls out every (v, ω) of a candidate grid for ``horizon_s`` seconds (unicycle arcs);
2. predicts each pedestrian with constant velocity over the same horizon;
3. scores the rollouts: progress along the shortest path to the goal (a cost-to-go field from Dijkstra on the
   occupancy grid inflated by the robot radius, with a wall-distance penalty), time-discounted penalties for
   intruding into pedestrians' space (steep below a safety gap, soft within the private zone), the same for
   obstacles, and a smoothness term;
4. executes the best command.

All rollouts are evaluated at once with numpy (candidates × steps × pedestrians).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim.episode import run_episode
from sim.geometry import wrap_angle
from sim.robot import ActionCodec
from sim.trace import EpisodeTrace
from sim.wrappers import PrivilegedWorld


@dataclass
class ExpertConfig:
    """Sampling grid, horizon and cost weights of the privileged expert."""

    n_speeds: int = 6  # candidate speeds, evenly in [0, v_max]
    n_rotations: int = 21  # candidate yaw rates, evenly in [−ω_max, ω_max]
    horizon_s: float = 2.0  # rollout horizon
    step_s: float = 0.2  # rollout resolution
    safety_margin_m: float = 0.15  # gap to pedestrians below which predicted intrusion costs w_contact per m·step
    comfort_m: float = 0.8  # soft penalty while the gap is below this (the private zone)
    obstacle_margin_m: float = 0.05  # gap to obstacles below which intrusion costs w_contact per m·step
    w_contact: float = 60.0  # weight of predicted intrusion (pedestrians and obstacles)
    w_progress: float = 1.0  # reward per metre of cost-to-go gained
    w_comfort: float = 0.6  # soft-penalty weight
    w_obstacle: float = 0.5  # near-obstacle penalty weight
    w_heading: float = 0.15  # penalty per rad of heading error at the end of the rollout
    w_smooth: float = 0.05  # penalty per rad/s change of ω
    discount_s: float = 1.5  # time constant of the discount on predicted penalties


class PrivilegedExpert:
    """Plans (v, ω) from the privileged state of the world: a :class:`sim.wrappers.WorldView` (what
    :class:`sim.wrappers.PrivilegedWorld` puts in ``info["world"]``) or, equivalently, an unwrapped
    :class:`sim.env.CrowdNavEnv` (the teacher's labels are computed env-side).

    Usage (as a driver: :class:`ExpertDriver`)::

        env = PrivilegedWorld(env)
        obs, info = env.reset(seed=0)
        expert = PrivilegedExpert()
        expert.reset(info["world"])
        action = info["action_codec"].encode(*expert.command(info["world"]))
    """

    def __init__(self, cfg: ExpertConfig | None = None):
        self.cfg = cfg or ExpertConfig()
        self._prev_w = 0.0

    def reset(self, env) -> None:
        """Plan the cost-to-go field of a new episode (call after ``env.reset``)."""
        rr = env.cfg.robot.radius_m
        self.nav = env.layout.nav(rr + self.cfg.obstacle_margin_m, wall_penalty=True)
        ctg = self.nav.distances_from(env.goal)
        finite = np.isfinite(ctg)
        self.ctg = np.where(finite, ctg, (ctg[finite].max() if finite.any() else 0.0) + 5.0)
        self._prev_w = 0.0
        r = env.cfg.robot
        c = self.cfg
        v = np.linspace(0.0, r.v_max_mps, c.n_speeds)
        w = np.linspace(-r.omega_max_radps, r.omega_max_radps, c.n_rotations)
        vv, ww = np.meshgrid(v, w, indexing="ij")
        self.cand = np.stack([vv.ravel(), ww.ravel()], -1)  # C x 2
        # the next control step itself, then every step_s up to the horizon
        self.times = np.concatenate([[env.cfg.dt_s], np.arange(1, int(round(c.horizon_s / c.step_s)) + 1) * c.step_s])

    def _ctg(self, xy: np.ndarray) -> np.ndarray:
        ij = self.nav.cell_of(xy)
        return self.ctg[ij[..., 0], ij[..., 1]]

    def _descent_heading(self, xy: np.ndarray) -> np.ndarray:
        """Direction of steepest descent of the cost-to-go at ``... x 2`` points (rad)."""
        ij = self.nav.cell_of(xy)
        h, w = self.ctg.shape
        i, j = ij[..., 0], ij[..., 1]
        gx = self.ctg[i, np.minimum(j + 1, w - 1)] - self.ctg[i, np.maximum(j - 1, 0)]
        gy = self.ctg[np.minimum(i + 1, h - 1), j] - self.ctg[np.maximum(i - 1, 0), j]
        return np.arctan2(-gy, -gx)

    def executed(self, omega: float) -> None:
        """The yaw rate actually executed this step, when another driver overrode the expert's choice (DAgger): the
        smoothness cost of the next step is relative to it."""
        self._prev_w = float(omega)

    def command(self, env) -> tuple[float, float]:
        """Best (v m/s, ω rad/s) for the env's current state."""
        k = int(np.argmin(self.costs(env)))
        vb, wb = self.cand[k]
        self._prev_w = float(wb)
        return float(vb), float(wb)

    def costs(self, env, cand: np.ndarray | None = None) -> np.ndarray:
        """The cost of every candidate (v, ω) — ``self.cand`` or a given ``C x 2`` table such as the policy's
        action grid — in the env's current state (lower is better; changes no state)."""
        c = self.cfg
        x, y, yaw = env.robot
        rr = env.cfg.robot.radius_m
        cand = self.cand if cand is None else np.asarray(cand, np.float64)
        v = cand[:, 0:1]
        w = cand[:, 1:2]
        t = self.times[None, :]
        # unicycle arcs, C x S
        straight = np.abs(w) < 1e-6
        ws = np.where(straight, 1.0, w)
        th = yaw + w * t
        px = np.where(straight, x + v * t * math.cos(yaw), x + v / ws * (np.sin(th) - math.sin(yaw)))
        py = np.where(straight, y + v * t * math.sin(yaw), y - v / ws * (np.cos(th) - math.cos(yaw)))
        traj = np.stack([px, py], -1)  # C x S x 2
        disc = np.exp(-self.times / c.discount_s)  # S
        cost = np.zeros(len(cand))
        # pedestrians (constant-velocity prediction)
        crowd = env.crowd
        if crowd.n:
            pp = crowd.pos[None, :, :] + self.times[:, None, None] * crowd.vel[None, :, :]  # S x N x 2
            d = np.linalg.norm(traj[:, :, None, :] - pp[None], axis=-1) - rr - crowd.radius[None, None, :]
            # predicted intrusion below the safety gap, discounted by how soon it happens: among rollouts that
            # all end in contact (a head-on walker in an aisle) this still prefers the one that dodges the most
            pen = np.clip(c.safety_margin_m - d, 0.0, None)
            cost += c.w_contact * (pen * disc[None, :, None]).sum((1, 2))
            soft = np.clip(c.comfort_m - d, 0.0, None) ** 2
            cost += c.w_comfort * (soft * disc[None, :, None]).sum((1, 2)) * c.step_s
        # obstacles
        clear = env.layout.clearance_at(traj) - rr  # exact geometry (the grid errs near corners)
        cost += c.w_contact * (np.clip(c.obstacle_margin_m - clear, 0.0, None) * disc[None]).sum(-1)
        cost += 1000.0 * (clear[:, 0] < 0.01)  # the next step itself would hit an obstacle
        cost += c.w_obstacle * (np.clip(0.25 - clear, 0.0, None) ** 2 * disc[None]).sum(-1)
        # progress along the shortest path, heading at the end, smoothness
        now = self._ctg(np.array([x, y]))
        end = self._ctg(traj[:, -1])
        cost -= c.w_progress * (now - end)
        d_goal = math.hypot(env.goal[0] - x, env.goal[1] - y)
        if d_goal > 0.5:
            head = self._descent_heading(traj[:, -1])
            cost += c.w_heading * np.abs(wrap_angle((yaw + w[:, 0] * self.times[-1]) - head))
        else:  # close to the goal: just get there
            cost += 2.0 * np.linalg.norm(traj - env.goal[None, None, :], axis=-1).min(1)
        cost += c.w_smooth * np.abs(w[:, 0] - self._prev_w)
        return cost


class ExpertDriver:
    """The privileged expert as a :class:`sim.episode.Driver`; its env must be wrapped in
    :class:`sim.wrappers.PrivilegedWorld` (it plans on ``info["world"]``). A long-horizon waypoint is ignored: the
    expert plans on the full map to the final goal (a reference, not a competitor)."""

    def __init__(self, expert: PrivilegedExpert | None = None) -> None:
        self.expert = expert or PrivilegedExpert()
        self.codec: ActionCodec | None = None
        self.last_command: tuple[float, float] = (0.0, 0.0)

    def reset(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        self.codec = info["action_codec"]
        self.expert.reset(info["world"])

    def act(self, obs: dict[str, np.ndarray], info: dict[str, Any]):
        self.last_command = self.expert.command(info["world"])  # (v m/s, ω rad/s) before encoding
        return self.codec.encode(*self.last_command)


def run_expert_episode(env, seed: int, expert: PrivilegedExpert | None = None, on_step=None) -> EpisodeTrace:
    """Run one episode of the expert on ``env`` (a gymnasium env, wrapped here in :class:`PrivilegedWorld`);
    returns its :class:`sim.trace.EpisodeTrace`.

    Args:
        on_step: optional ``callback(transition)`` for every :class:`sim.episode.Transition` (the reset included).
    """
    return run_episode(PrivilegedWorld(env), ExpertDriver(expert), seed, "expert", on_step=on_step)
