"""SARL*-OM: SARL's attention value network + a local occupancy map of static obstacles + danger-zone reward.

The paper's SARL*-OM baseline combines three works; this module reproduces each part in our simulator:

* **SARL** (Chen, Liu, Kreiss, Alahi, "Crowd-Robot Interaction: Crowd-aware Robot Navigation with Attention-based
  Deep Reinforcement Learning", ICRA 2019): a value network V(joint state) over the robot state and every human's
  state in a goal-aligned frame, with self-attention pooling of human-robot interaction features, trained by
  imitation of a demonstrator and then deep V-learning; actions by one-step lookahead.
* **OM** (Liu, Dugas, Cesari, Siegwart, Dubé, "Robot Navigation in Crowded Environments Using Deep Reinforcement
  Learning", IROS 2020): static obstacles enter the value network as a local *angular map* — the range scan of the
  static map binned into angular sectors, the nearest range per sector — encoded by an MLP and joined to the crowd
  feature before the value MLP (humans stay in the attention branch, walls in the map branch).
* **Danger zones** (Samsani & Muhammad, "Socially Compliant Robot Navigation in Crowded Environment by Human
  Behavior Resemblance Using Deep Reinforcement Learning", RA-L 2021): each human carries a velocity-dependent
  zone — a sector centred on its walking direction whose radius grows and whose opening narrows with its speed —
  and the reward penalises the robot for being inside it.

What it observes (``obs_mode: privileged``; built from the ``env`` object, never from ``obs``):
perfect tracks (:func:`rl.baselines.common.tracked_pedestrians`: true positions, velocities, radii) of the
``max_humans`` nearest pedestrians whose centre is within ``sensor_range_m``; a ray-cast of the *static* map
(``om_rays`` rays over 360°, ``om_range_m``) from the robot centre; the goal (or the waypoint of long-horizon runs);
its own pose and last commanded speed.

Joint state (CrowdNav's ``rotate()``), frame: origin at the robot, x toward the goal::

    self   (6)    d_g, v_pref, θ (heading − goal direction, wrapped), ρ_robot, v_x, v_y
    human  (K x 7) p_x, p_y, v_x, v_y, ρ_h, |p| (distance), ρ_h + ρ_robot     (K = max_humans, padded, + mask)
    om     (S)    closeness 1 − r/om_range_m of the nearest static hit in each of S sectors (0 = free), sector
                  k covering angles [−π + k·2π/S, −π + (k+1)·2π/S) in the goal frame

Network (:class:`SarlOMValue`, SARL's sizes): mlp1 (13 → 150 → 100) per human; mlp2 (100 → 100 → 50) interaction
features; attention MLP ([mlp1 ‖ masked mean of mlp1] 200 → 100 → 100 → 1) → masked softmax weights; crowd
feature = Σ weights · mlp2 (zero for an empty crowd); om encoder (S → 64 → 32); mlp3 ([self ‖ crowd ‖ om] 88 → 150 →
100 → 100 → 1) = V.

Policy: one-step lookahead over the robot's 5 x 21 (v, ω) grid (:func:`sim.robot.action_grid`): every action is
held for ``lookahead_s`` = 0.25 s (CrowdNav's decision period; exact unicycle arcs, events checked at every 0.1 s
control step on the way), the humans move with constant velocity; the value of an action is
R(s, a) + γ^(τ·v_pref) · V(s') (no bootstrap where R ends the episode), all 105 candidates in one batched forward;
argmax (ε-greedy during RL), executed for one control step and re-planned (receding horizon).

Reward R (per control step Δt; CrowdNav's terms with Samsani's zones)::

    +1                              reaching the goal (d_g ≤ goal radius)                       terminal
    −0.25                           collision: gap to a human ≤ 0, or static clearance ≤ ρ_robot terminal
    0.5 · (gap − 0.2) · Δt          discomfort: nearest human gap below 0.2 m (CrowdNav)
    − w_dz · Σ_h depth_h · Δt       danger zones: human h's zone is the sector of radius
                                    R_h = ρ_h + ρ_robot + dz_margin_m + dz_time_s · |v_h| and full opening
                                    Θ_h = 11π/6 · exp(−1.4 |v_h|) + π/6 (a full circle when standing) about
                                    its walking direction; depth_h = (R_h − d)/(R_h − ρ_h − ρ_robot) ∈ [0, 1]
    + w_prog · (d_g(s) − d_g(s'))   progress toward the goal (our addition, see below)

Training (:func:`train`, CrowdNav's procedure):

1. imitation: ``il_episodes`` (default: the teacher's ``bc_episodes``) episodes of the privileged expert on the
   training scenes (``training_pairs(cfg)``), observed by :class:`SarlObserver`; each visited joint state gets the
   discounted return of R along the episode (CrowdNav's IL value targets; timeouts are dropped as in CrowdNav);
   V is regressed on them (MSE, ``il_epochs``), and the transitions seed the replay memory (CrowdNav keeps its IL
   memory for RL);
2. deep V-learning: ``rl_iterations`` iterations of ``episodes_per_iter`` ε-greedy lookahead episodes (ε linear
   from ``epsilon_start`` to ``epsilon_end`` over ``epsilon_decay_episodes``) collected by ``cfg.workers``
   processes with a copy of the current weights; transitions (s, R, s', terminal) in a replay memory of
   ``capacity``; ``train_batches`` minibatches of TD targets R + γ^(Δt·v_pref) · V_target(s') per iteration; the
   target network is copied every ``target_update_episodes`` episodes. ``out/rl/`` holds a checkpoint (weights,
   optimiser, replay, counters) every ``checkpoint_every`` iterations, so ``--resume`` continues from there.

Deviations from the papers (and why):

* Unicycle robot with our 5 x 21 (v, ω) grid and Δt = 0.1 s (CrowdNav: holonomic 80 actions or unicycle with
  ±π/4 rotations, Δt = 0.25 s): the action space of the benchmark. The lookahead keeps CrowdNav's 0.25 s: over a
  single 0.1 s step the candidates' values differ by less than the value network's error.
* Mirror augmentation (y -> -y in the goal frame) of the imitation data and of half of each TD minibatch, as our
  teacher's cloning does: with few demonstrations V's dependence on heading was otherwise lopsided.
* Static obstacles: CrowdNav has none. The angular map follows Liu et al.; the collision test of R uses the nearest
  static-scan hit (the static map is privileged information in our benchmark, as for DRL-VO).
* Progress term w_prog = 0.1 per m: our episodes are 6 m among walls and timeouts at 40 s; with γ = 0.9 per
  second the terminal +1 alone gives a value slope of a few hundredths per metre, too flat for the lookahead
  to find its way around obstacles within a 10-minute budget. Danger-zone constants (dz_time_s, dz_margin_m,
  w_dz) are our choices scaled to Δt; the opening angle is the speed-dependent field of Samsani & Muhammad
  (after Kitazawa & Fujiyama).
* Value targets: TD targets with a frozen target network computed when a minibatch is drawn (CrowdNav computes
  them when the episode is stored), bootstrapped after a timeout (truncation, not a terminal state); transitions
  are collected in parallel batches of episodes rather than one episode per update; Adam instead of SGD.
* Budget: the number of expert episodes matches our teacher's; RL runs a few hundred episodes (CrowdNav: 10k), sized
  to train in about ten minutes on two CPU cores in the default profile.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pipeline.core.errors import ConfigError, CorruptArtifactError
from rl.baselines.common import (
    collect_expert_episodes,
    load_baseline,
    save_baseline,
    to_robot_frame,
    tracked_pedestrians,
    training_pairs,
)
from sim.env import CrowdNavEnv, SimConfig
from sim.geometry import wrap_angle
from sim.robot import action_grid

NAME = "sarl_om"
SELF_DIM = 6
HUMAN_DIM = 7
KEYS = ("self", "humans", "mask", "om")  # the joint state's arrays (module docstring)


@dataclass
class Config:
    """SARL*-OM options: what it observes, its reward, and the training budget (the ``default`` profile)."""

    # observation
    sensor_range_m: float = 4.0  # pedestrians (perfect tracks) whose centre is within this range are seen
    max_humans: int = 10  # K: the nearest this many are kept (padded + masked below)
    om_rays: int = 180  # rays of the static-map scan (360°)
    om_range_m: float = 4.0  # range of that scan and of the angular map
    om_sectors: int = 36  # S: angular-map sectors over 360° (10° each)
    # reward (module docstring)
    gamma: float = 0.9  # discount per second at v_pref: γ^(Δt·v_pref) per step (CrowdNav)
    lookahead_s: float = 0.25  # how long the lookahead holds each action (CrowdNav's time step)
    success_reward: float = 1.0
    collision_penalty: float = -0.25
    discomfort_m: float = 0.2  # CrowdNav discomfort distance (gap to a human body)
    discomfort_factor: float = 0.5  # per m of intrusion per second
    dz_weight: float = 0.25  # danger-zone penalty per second at full depth
    dz_margin_m: float = 0.2  # zone radius of a standing human beyond body contact
    dz_time_s: float = 1.0  # zone radius grows by this many seconds of the human's walk
    progress_weight: float = 0.1  # per m of progress toward the goal
    # imitation
    il_episodes: int = 0  # expert episodes; 0 = the teacher's teacher.bc_episodes
    il_epochs: int = 30
    il_lr: float = 1e-3
    batch_size: int = 128
    # deep V-learning
    rl_iterations: int = 40
    episodes_per_iter: int = 12  # spread over cfg.workers processes
    train_batches: int = 100  # minibatches per iteration (CrowdNav: 100 of 100 per episode)
    rl_lr: float = 2e-4
    target_update_episodes: int = 48  # copy the value network into the target network this often
    epsilon_start: float = 0.5
    epsilon_end: float = 0.1
    epsilon_decay_episodes: int = 300
    capacity: int = 100_000  # replay memory (transitions)
    checkpoint_every: int = 5  # iterations between checkpoints in out/rl/ (resume)

    def validate(self) -> None:
        """Raises ConfigError naming the first bad field."""
        positive = ("sensor_range_m", "om_range_m", "il_lr", "rl_lr", "discomfort_m", "dz_margin_m", "lookahead_s")
        for k in positive:
            if not getattr(self, k) > 0:
                raise ConfigError(f"sarl_om.{k}: expected > 0, got {getattr(self, k)}")
        counts = ("max_humans", "om_rays", "om_sectors", "il_epochs", "batch_size", "episodes_per_iter",
                  "train_batches", "target_update_episodes", "epsilon_decay_episodes", "capacity",
                  "checkpoint_every")
        for k in counts:
            v = getattr(self, k)
            if not isinstance(v, int) or v < 1:
                raise ConfigError(f"sarl_om.{k}: expected an integer >= 1, got {v!r}")
        if self.il_episodes < 0 or self.rl_iterations < 0:
            raise ConfigError(f"sarl_om: il_episodes and rl_iterations must be >= 0, got {self.il_episodes}, "
                              f"{self.rl_iterations}")
        if self.om_rays < self.om_sectors:
            raise ConfigError(f"sarl_om.om_rays: expected >= om_sectors ({self.om_sectors}), got {self.om_rays}")
        if not 0.0 < self.gamma <= 1.0:
            raise ConfigError(f"sarl_om.gamma: expected in (0, 1], got {self.gamma}")
        if not 0.0 <= self.epsilon_end <= self.epsilon_start <= 1.0:
            raise ConfigError(f"sarl_om: expected 0 <= epsilon_end <= epsilon_start <= 1, got "
                              f"{self.epsilon_end}, {self.epsilon_start}")
        if min(self.dz_weight, self.dz_time_s, self.discomfort_factor, self.progress_weight) < 0:
            raise ConfigError("sarl_om: dz_weight, dz_time_s, discomfort_factor and progress_weight must be >= 0")
        if self.success_reward <= 0 or self.collision_penalty >= 0:
            raise ConfigError(f"sarl_om: expected success_reward > 0 and collision_penalty < 0, got "
                              f"{self.success_reward}, {self.collision_penalty}")


# Fields the driver needs at run time (stored in policy.json's observation_space).
_RUNTIME = ("sensor_range_m", "max_humans", "om_rays", "om_range_m", "om_sectors", "gamma", "lookahead_s",
            "success_reward",
            "collision_penalty", "discomfort_m", "discomfort_factor", "dz_weight", "dz_margin_m", "dz_time_s",
            "progress_weight")


def inputs(cfg) -> list[Path]:
    """Nothing but the simulator."""
    return []


# --------------------------------------------------------------------------------------------------- network
def _mlp(sizes: list[int], last_relu: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    for k in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[k], sizes[k + 1]))
        if k < len(sizes) - 2 or last_relu:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class SarlOMValue(nn.Module):
    """V(joint state): SARL's attention network with an angular-map branch (sizes in the module docstring)."""

    def __init__(self, om_sectors: int, mlp1: tuple[int, ...] = (150, 100), mlp2: tuple[int, ...] = (100, 50),
                 attention: tuple[int, ...] = (100, 100), om: tuple[int, ...] = (64, 32),
                 mlp3: tuple[int, ...] = (150, 100, 100)) -> None:
        super().__init__()
        self.spec = {"om_sectors": om_sectors, "mlp1": list(mlp1), "mlp2": list(mlp2), "attention": list(attention),
                     "om": list(om), "mlp3": list(mlp3)}
        self.mlp1 = _mlp([SELF_DIM + HUMAN_DIM, *mlp1], True)
        self.mlp2 = _mlp([mlp1[-1], *mlp2], False)
        self.attention = _mlp([2 * mlp1[-1], *attention, 1], False)
        self.om = _mlp([om_sectors, *om], True)
        self.mlp3 = _mlp([SELF_DIM + mlp2[-1] + om[-1], *mlp3, 1], False)

    def forward(self, self_state: torch.Tensor, humans: torch.Tensor, mask: torch.Tensor,
                om: torch.Tensor) -> torch.Tensor:
        """``B x 6``, ``B x K x 7``, ``B x K`` (1 = present), ``B x S`` -> ``B`` values."""
        b, k, _ = humans.shape
        m = mask.to(humans.dtype)
        x = torch.cat([self_state[:, None, :].expand(b, k, SELF_DIM), humans], -1)
        e = self.mlp1(x)  # B x K x 100
        glob = (e * m[..., None]).sum(1) / m.sum(1, keepdim=True).clamp(min=1.0)
        scores = self.attention(torch.cat([e, glob[:, None, :].expand_as(e)], -1))[..., 0]
        w = torch.softmax(scores.masked_fill(m <= 0, -1e9), -1) * m  # an empty crowd: all weights 0
        crowd = (w[..., None] * self.mlp2(e)).sum(1)
        return self.mlp3(torch.cat([self_state, crowd, self.om(om)], -1))[:, 0]


def build(net: dict[str, Any]) -> SarlOMValue:
    """The network described by ``policy.json``'s ``net``."""
    return SarlOMValue(int(net["om_sectors"]), tuple(net["mlp1"]), tuple(net["mlp2"]), tuple(net["attention"]),
                       tuple(net["om"]), tuple(net["mlp3"]))


def _tensors(batch: dict[str, np.ndarray]) -> list[torch.Tensor]:
    return [torch.as_tensor(batch[k], dtype=torch.float32) for k in KEYS]


def mirror(js: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The joint states reflected about the goal direction (y -> -y): a world that is as likely as the original
    (augmentation, as the teacher's cloning mirrors its data)."""
    flip_self = np.array([1, 1, -1, 1, 1, -1], np.float32)
    flip_human = np.array([1, -1, 1, -1, 1, 1, 1], np.float32)
    return {"self": js["self"] * flip_self, "humans": js["humans"] * flip_human, "mask": js["mask"],
            "om": js["om"][..., ::-1].copy()}


# ------------------------------------------------------------------------------------------------ perception
@dataclass
class Scene:
    """What the robot sees now, in its own frame (x forward, y left): ``goal`` (2,), ``humans`` M x 5 [x, y, vx,
    vy, radius] (M <= max_humans, nearest first), ``hits`` P x 2 static-scan hits, ``speed`` (m/s, last command),
    ``radius`` ρ_robot, ``v_pref`` and ``goal_radius`` (m)."""

    goal: np.ndarray
    humans: np.ndarray
    hits: np.ndarray
    speed: float
    radius: float
    v_pref: float
    goal_radius: float


def perceive(env: CrowdNavEnv, goal_xy: np.ndarray | None, oc: Config) -> Scene:
    """The :class:`Scene` of the env's current state toward ``goal_xy`` (world frame; the env's goal if None)."""
    x, y, yaw = env.robot
    ang = np.arange(oc.om_rays) * (2 * math.pi / oc.om_rays)  # robot frame
    r = np.asarray(env.layout.geometry.raycast(np.array([x, y]), yaw + ang, oc.om_range_m), np.float64)
    hit = r < oc.om_range_m - 1e-6
    hits = np.stack([r[hit] * np.cos(ang[hit]), r[hit] * np.sin(ang[hit])], -1)
    rc = env.cfg.robot
    return Scene(goal=to_robot_frame(env, env.goal if goal_xy is None else goal_xy).astype(np.float64),
                 humans=tracked_pedestrians(env, oc.sensor_range_m)[:oc.max_humans].astype(np.float64),
                 hits=hits, speed=float(env.robot_v[0]), radius=rc.radius_m, v_pref=rc.v_max_mps,
                 goal_radius=env.cfg.goal_radius_m)


def joint_state(sc: Scene, pos: np.ndarray, theta: np.ndarray, vel: np.ndarray, hpos: np.ndarray,
                oc: Config) -> dict[str, np.ndarray]:
    """The joint states (module docstring) of ``B`` robot states in the scene's frame: ``pos`` B x 2, ``theta``
    B, ``vel`` B x 2 (velocity), with the humans at ``hpos`` (M x 2) moving with ``sc.humans`` velocities.

    Returns ``self`` B x 6, ``humans`` B x K x 7, ``mask`` B x K, ``om`` B x S (float32)."""
    b, k, m = len(pos), oc.max_humans, len(hpos)
    d = sc.goal[None, :] - pos
    rot = np.arctan2(d[:, 1], d[:, 0])
    c, s = np.cos(rot)[:, None], np.sin(rot)[:, None]

    def rotate(v: np.ndarray) -> np.ndarray:  # ... x 2 vectors into each goal frame (B leading)
        cc, ss = (c, s) if v.ndim == 2 else (c[..., None], s[..., None])
        return np.stack([v[..., 0] * cc[..., 0] + v[..., 1] * ss[..., 0],
                         v[..., 1] * cc[..., 0] - v[..., 0] * ss[..., 0]], -1)

    out = {"self": np.zeros((b, SELF_DIM)), "humans": np.zeros((b, k, HUMAN_DIM)), "mask": np.zeros((b, k)),
           "om": np.zeros((b, oc.om_sectors))}
    out["self"][:, 0] = np.hypot(d[:, 0], d[:, 1])
    out["self"][:, 1] = sc.v_pref
    out["self"][:, 2] = wrap_angle(theta - rot)
    out["self"][:, 3] = sc.radius
    out["self"][:, 4:6] = rotate(vel)
    if m:
        rel = rotate(hpos[None, :, :] - pos[:, None, :])  # B x M x 2
        hv = rotate(np.broadcast_to(sc.humans[None, :, 2:4], (b, m, 2)))
        hr = sc.humans[:, 4]
        out["humans"][:, :m] = np.concatenate(
            [rel, hv, np.broadcast_to(hr, (b, m))[..., None], np.hypot(rel[..., 0], rel[..., 1])[..., None],
             np.broadcast_to(hr + sc.radius, (b, m))[..., None]], -1)
        out["mask"][:, :m] = 1.0
    if len(sc.hits):
        rel = rotate(sc.hits[None, :, :] - pos[:, None, :])  # B x P x 2
        close = 1.0 - np.clip(np.hypot(rel[..., 0], rel[..., 1]) / oc.om_range_m, 0.0, 1.0)
        sector = np.floor((np.arctan2(rel[..., 1], rel[..., 0]) + math.pi) / (2 * math.pi) * oc.om_sectors)
        sector = np.clip(sector.astype(np.intp), 0, oc.om_sectors - 1)
        np.maximum.at(out["om"], (np.repeat(np.arange(b), sector.shape[1]), sector.ravel()), close.ravel())
    return {key: v.astype(np.float32) for key, v in out.items()}


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
    B). Terms in the module docstring."""
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


def current_state(sc: Scene, oc: Config) -> dict[str, np.ndarray]:
    """The joint state of the robot now (one row)."""
    return joint_state(sc, np.zeros((1, 2)), np.zeros(1), np.array([[sc.speed, 0.0]]), sc.humans[:, :2], oc)


class Lookahead:
    """SARL's one-step lookahead over the action grid (module docstring): each action is held for
    ``lookahead_s`` (CrowdNav's decision period), checked for events at every control step on the way, and
    re-planned after one control step (receding horizon)."""

    def __init__(self, model: SarlOMValue, oc: Config, env: CrowdNavEnv) -> None:
        self.model, self.oc = model, oc
        self.dt = env.cfg.dt_s
        self.grid = action_grid(env.cfg.robot)  # A x 2 (v, ω)
        n = max(1, int(math.floor(oc.lookahead_s / self.dt + 1e-9)))
        self.times = np.unique(np.r_[np.arange(1, n + 1) * self.dt, max(oc.lookahead_s, self.dt)])  # J
        v, w = self.grid[:, :1], self.grid[:, 1:]
        straight = np.abs(w) < 1e-6
        ws = np.where(straight, 1.0, w)
        th = w * self.times[None, :]  # A x J
        self.path = np.stack([np.where(straight, v * self.times, v / ws * np.sin(th)),
                              np.where(straight, 0.0, v / ws * (1.0 - np.cos(th)))], -1)  # A x J x 2, robot frame
        self.theta = th[:, -1]
        self.vel = np.stack([v[:, 0] * np.cos(self.theta), v[:, 0] * np.sin(self.theta)], -1)

    def values(self, sc: Scene) -> np.ndarray:
        """R(s, a) + γ^(τ·v_pref) · V(s'_a) for every action a of the grid (A), τ = the lookahead time; R is the
        first event (collision, goal) on the way, else the reward of arriving at s'_a over τ."""
        d0 = float(np.hypot(*sc.goal))
        r, done = reward(sc, self.path[:, -1], sc.humans[:, :2] + self.times[-1] * sc.humans[:, 2:4], d0,
                         self.times[-1], self.oc)
        for j in range(len(self.times) - 2, -1, -1):  # earlier events override later ones
            rj, dj = reward(sc, self.path[:, j], sc.humans[:, :2] + self.times[j] * sc.humans[:, 2:4], d0,
                            self.times[j], self.oc)
            r, done = np.where(dj, rj, r), done | dj
        nxt = joint_state(sc, self.path[:, -1], self.theta, self.vel,
                          sc.humans[:, :2] + self.times[-1] * sc.humans[:, 2:4], self.oc)
        m = max(1, len(sc.humans))  # padding changes no value (masked): run the network on the present humans only
        nxt["humans"], nxt["mask"] = nxt["humans"][:, :m], nxt["mask"][:, :m]
        with torch.no_grad():
            v = self.model(*_tensors(nxt)).numpy().astype(np.float64)
        return r + self.oc.gamma ** (self.times[-1] * sc.v_pref) * np.where(done, 0.0, v)

    def act(self, sc: Scene, epsilon: float = 0.0, rng: np.random.Generator | None = None) -> int:
        """The argmax action index (uniformly random with probability ``epsilon``)."""
        if epsilon > 0 and rng is not None and rng.random() < epsilon:
            return int(rng.integers(len(self.grid)))
        return int(np.argmax(self.values(sc)))


class SarlObserver:
    """The joint state of every step plus ``arrival``: R's shaping terms of arriving in this state (progress since
    the previous step, discomfort, danger zones); for :func:`collect_expert_episodes` (picklable with a config)."""

    def __init__(self, oc: Config) -> None:
        self.oc = oc
        self.d_prev = math.nan

    def reset(self, env: CrowdNavEnv, obs: dict | None = None) -> None:
        self.d_prev = math.nan

    def __call__(self, env: CrowdNavEnv, obs: dict | None = None) -> dict[str, np.ndarray]:
        sc = perceive(env, None, self.oc)
        here = np.zeros((1, 2))
        d = float(np.hypot(*sc.goal))
        r, _ = reward(sc, here, sc.humans[:, :2], d if math.isnan(self.d_prev) else self.d_prev, env.cfg.dt_s,
                      self.oc)
        self.d_prev = d
        return {**{k: v[0] for k, v in current_state(sc, self.oc).items()}, "arrival": r.astype(np.float32)[0]}


# --------------------------------------------------------------------------------------------------- driver
class Driver:
    """Drives with the saved value network's lookahead (see :mod:`rl.baselines.common`)."""

    def __init__(self, ckpt: Path) -> None:
        self.model, desc = load_baseline(Path(ckpt), NAME, build)
        try:
            self.oc = replace(Config(), **{k: desc["observation_space"][k] for k in _RUNTIME})
        except (KeyError, TypeError) as e:
            raise CorruptArtifactError(f"{Path(ckpt) / 'policy.json'}: observation_space lacks {e}") from None
        self.look: Lookahead | None = None
        self.last_om: np.ndarray | None = None

    def reset(self, env: CrowdNavEnv, obs: dict | None = None) -> None:
        self.look = Lookahead(self.model, self.oc, env)

    def act(self, env: CrowdNavEnv, obs: dict | None = None, waypoint: np.ndarray | None = None) -> int:
        if self.look is None:
            self.reset(env, obs)
        sc = perceive(env, waypoint, self.oc)
        self.last_om = current_state(sc, self.oc)["om"][0]
        return self.look.act(sc)

    def bev_panel(self) -> np.ndarray | None:
        """The angular map as an image (rows: range bins near to far; columns: sectors, goal direction centred;
        1 = a static hit at or before that range)."""
        if self.last_om is None:
            return None
        bins = (np.arange(32) + 0.5) / 32  # closeness 1 - r/R of each range bin: near rows first
        return (self.last_om[None, :] >= 1.0 - bins[:, None]).astype(np.float32)


# ------------------------------------------------------------------------------------------------- rollouts
_WORKER: dict[str, Any] = {}


def _init_worker(sim_cfg: SimConfig, oc: Config, net: dict[str, Any]) -> None:
    torch.set_num_threads(1)
    _WORKER.update(sim_cfg=sim_cfg, oc=oc, model=build(net).eval(), envs={})


def _env(pair: tuple[str, float]) -> CrowdNavEnv:
    envs = _WORKER["envs"]
    if pair not in envs:
        envs[pair] = CrowdNavEnv(config=replace(_WORKER["sim_cfg"], scene=pair[0], density=pair[1], obs_mode="state",
                                                action_type="discrete", info_level="basic"))
    return envs[pair]


def _run_episodes(state: dict[str, np.ndarray], jobs: list[tuple[str, float, int, float]]) -> list[dict]:
    """Runs ε-greedy lookahead episodes ``(scene, density, seed, ε)`` with weights ``state`` in this process."""
    model: SarlOMValue = _WORKER["model"]
    model.load_state_dict({k: torch.as_tensor(v) for k, v in state.items()})
    oc: Config = _WORKER["oc"]
    return [_episode(_env((scene, density)), model, oc, seed, eps) for scene, density, seed, eps in jobs]


def _episode(env: CrowdNavEnv, model: SarlOMValue, oc: Config, seed: int, epsilon: float) -> dict:
    """One episode: its transitions (``s_*``, ``n_*`` joint states, ``reward``, ``done``), outcome and actions."""
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    look = Lookahead(model, oc, env)
    obs = SarlObserver(oc)
    obs.reset(env)
    states = [obs(env)]
    actions, rewards = [], []
    while True:
        a = look.act(perceive(env, None, oc), epsilon, rng)
        _, _, term, trunc, info = env.step(a)
        actions.append(a)
        states.append(obs(env))
        outcome = info["outcome"]
        if outcome == "success":
            rewards.append(oc.success_reward)
        elif term:
            rewards.append(oc.collision_penalty)
        else:
            rewards.append(float(states[-1]["arrival"]))
        if term or trunc:
            break
    cur = {k: np.stack([s[k] for s in states[:-1]]) for k in KEYS}
    nxt = {k: np.stack([s[k] for s in states[1:]]) for k in KEYS}
    done = np.zeros(len(rewards), bool)
    done[-1] = bool(term)
    return {**{f"s_{k}": v for k, v in cur.items()}, **{f"n_{k}": v for k, v in nxt.items()},
            "reward": np.asarray(rewards, np.float32), "done": done, "outcome": outcome or "timeout",
            "actions": np.asarray(actions)}


class Replay:
    """Ring buffer of transitions (s, R, s', terminal)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.data: dict[str, np.ndarray] = {}
        self.size = 0
        self.head = 0

    def push(self, batch: dict[str, np.ndarray]) -> None:
        n = len(batch["reward"])
        if not self.data:
            self.data = {k: np.zeros((self.capacity, *v.shape[1:]), v.dtype) for k, v in batch.items()}
        idx = (self.head + np.arange(n)) % self.capacity
        for k, v in batch.items():
            self.data[k][idx] = v[-self.capacity:] if n > self.capacity else v
        self.head = int((self.head + n) % self.capacity)
        self.size = min(self.capacity, self.size + n)

    def sample(self, rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
        idx = rng.integers(self.size, size=n)
        return {k: v[idx] for k, v in self.data.items()}


TRANSITION_KEYS = tuple(f"{p}_{k}" for p in ("s", "n") for k in KEYS) + ("reward", "done")


# ------------------------------------------------------------------------------------------------- training
def _imitation_data(cfg, oc: Config, n_episodes: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict]:
    """Expert episodes -> (value-regression data {KEYS, target}, transitions for the replay, stats)."""
    data = collect_expert_episodes(cfg.sim, training_pairs(cfg), n_episodes, cfg.seed,
                                   functools.partial(SarlObserver, oc), cfg.workers, obs_mode="state",
                                   action_type="discrete", progress=cfg.progress, desc="sarl_om: expert episodes")
    ep = data["episode"]
    last = data["done"]
    collided = last & (data["reward"] <= 0.5 * cfg.sim.reward.collision)  # the paper's reward's collision term
    succeeded = last & data["success"]
    # R of step t is the arrival reward of step t + 1; the last step's is the outcome's (0 after a timeout)
    r = np.where(last, 0.0, np.roll(data["arrival"], -1)).astype(np.float32)
    r = np.where(succeeded, oc.success_reward, np.where(collided, oc.collision_penalty, r)).astype(np.float32)
    step_gamma = oc.gamma ** (cfg.sim.dt_s * cfg.sim.robot.v_max_mps)
    target = np.zeros_like(r)
    acc = 0.0
    for t in range(len(r) - 1, -1, -1):  # discounted return per episode
        acc = r[t] + (0.0 if last[t] else step_gamma * acc)
        target[t] = acc
    keep_ep = np.unique(ep[succeeded | collided])  # CrowdNav's IL keeps successes and collisions
    keep = np.isin(ep, keep_ep)
    il = {k: data[k][keep] for k in KEYS}
    il["target"] = target[keep]
    nxt = {f"n_{k}": np.where(last[keep].reshape(-1, *[1] * (data[k].ndim - 1)), data[k][keep],
                              np.roll(data[k], -1, 0)[keep]) for k in KEYS}
    trans = {**{f"s_{k}": data[k][keep] for k in KEYS}, **nxt, "reward": r[keep], "done": last[keep]}
    stats = {"expert_episodes": n_episodes, "expert_frames": int(len(r)), "il_episodes_kept": int(len(keep_ep)),
             "expert_success_rate": float(succeeded.sum() / max(1, last.sum()))}
    return il, trans, stats


def regress(model: SarlOMValue, data: dict[str, np.ndarray], epochs: int, batch: int, lr: float, seed: int,
            log=None) -> float:
    """MSE regression of V on ``data['target']`` and on the mirrored states (imitation); returns the last epoch's
    mean loss."""
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    rng = np.random.default_rng(seed)
    both = {k: np.concatenate([data[k], mirror(data)[k]]) for k in KEYS}
    x = _tensors(both)
    y = torch.as_tensor(np.concatenate([data["target"]] * 2), dtype=torch.float32)
    n = len(y)
    mean = math.nan
    if n == 0:  # no expert episode reached the goal (timeouts are dropped, as CrowdNav does)
        logging.getLogger("icrowdnav").warning("SARL*-OM: no imitation targets (no expert episode succeeded); "
                                               "imitation skipped")
        return mean
    model.train()
    for epoch in range(epochs):
        perm = torch.as_tensor(rng.permutation(n))
        losses = []
        for i in range(0, n, batch):
            idx = perm[i:i + batch]
            loss = nn.functional.mse_loss(model(*(t[idx] for t in x)), y[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
        mean = float(np.mean(losses))
        if log is not None:
            log.add("imitation", epoch, value_mse=mean)
    model.eval()
    return mean


def td_update(model: SarlOMValue, target: SarlOMValue, opt: torch.optim.Optimizer, batch: dict[str, np.ndarray],
              step_gamma: float) -> float:
    """One deep V-learning step: MSE of V(s) to R + γ̄ · V_target(s') (no bootstrap when terminal); the second half
    of the batch is mirrored (:func:`mirror`)."""
    half = len(batch["reward"]) // 2

    def states(prefix: str) -> list[torch.Tensor]:
        js = {k: batch[f"{prefix}_{k}"] for k in KEYS}
        flipped = mirror({k: v[half:] for k, v in js.items()})
        return _tensors({k: np.concatenate([v[:half], flipped[k]]) for k, v in js.items()})

    s, n = states("s"), states("n")
    with torch.no_grad():
        v_next = target(*n)
    y = torch.as_tensor(batch["reward"]) + step_gamma * v_next * torch.as_tensor(~batch["done"], dtype=torch.float32)
    loss = nn.functional.mse_loss(model(*s), y)
    opt.zero_grad()
    loss.backward()
    opt.step()
    return float(loss.item())


def _save_state(path: Path, model: SarlOMValue, target: SarlOMValue, opt: torch.optim.Optimizer, replay: Replay,
                counters: dict[str, Any]) -> None:
    """``out/rl/state.pt`` (weights, optimiser, counters) and ``replay.npz``, each written atomically."""
    path.mkdir(parents=True, exist_ok=True)
    tmp = path / "replay.tmp.npz"
    np.savez(tmp, size=replay.size, head=replay.head, **replay.data)
    os.replace(tmp, path / "replay.npz")
    torch.save({"model": model.state_dict(), "target": target.state_dict(), "opt": opt.state_dict(),
                "counters": counters}, path / "state.tmp.pt")
    os.replace(path / "state.tmp.pt", path / "state.pt")


def _load_state(path: Path, model: SarlOMValue, target: SarlOMValue, opt: torch.optim.Optimizer,
                replay: Replay) -> dict[str, Any]:
    try:
        st = torch.load(path / "state.pt", weights_only=False)
        model.load_state_dict(st["model"])
        target.load_state_dict(st["target"])
        opt.load_state_dict(st["opt"])
        with np.load(path / "replay.npz") as z:
            replay.data = {k: z[k] for k in TRANSITION_KEYS}
            replay.size, replay.head = int(z["size"]), int(z["head"])
    except (OSError, KeyError, RuntimeError, ValueError) as e:
        raise CorruptArtifactError(f"{path}: cannot resume SARL*-OM ({type(e).__name__}: {e}); rerun with "
                                   "--overwrite") from None
    return st["counters"]


def train(cfg, out: Path, log) -> dict[str, Any]:
    """Imitation of the expert, then deep V-learning (module docstring); writes the checkpoint into ``out``."""
    oc: Config = cfg.sarl_om
    oc.validate()
    t0 = time.time()
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    out = Path(out)
    rl_dir = out / "rl"
    model = SarlOMValue(oc.om_sectors)
    target = SarlOMValue(oc.om_sectors)
    opt = torch.optim.Adam(model.parameters(), lr=oc.rl_lr)
    replay = Replay(oc.capacity)
    step_gamma = oc.gamma ** (cfg.sim.dt_s * cfg.sim.robot.v_max_mps)
    pairs = training_pairs(cfg)
    if getattr(cfg, "resume", False) and (rl_dir / "state.pt").is_file():
        c = _load_state(rl_dir, model, target, opt, replay)
    else:
        n_il = oc.il_episodes or cfg.teacher.bc_episodes
        il, trans, stats = _imitation_data(cfg, oc, n_il)
        il_loss = regress(model, il, oc.il_epochs, oc.batch_size, oc.il_lr, cfg.seed, log)
        target.load_state_dict(model.state_dict())
        replay.push(trans)
        c = {"iteration": 0, "episodes": 0, "env_steps": 0, "updates": 0, "since_target": 0,
             "wall_s": time.time() - t0, "il_loss": il_loss, **stats}
        _save_state(rl_dir, model, target, opt, replay, c)
    rng = np.random.default_rng(cfg.seed + 7)
    t_start = time.time() - c["wall_s"]  # wall time accumulates over resumed runs
    pool = None
    if cfg.workers > 1 and c["iteration"] < oc.rl_iterations:
        import multiprocessing as mp

        pool = ProcessPoolExecutor(cfg.workers, mp_context=mp.get_context("fork"), initializer=_init_worker,
                                   initargs=(cfg.sim, oc, model.spec))
    else:
        _init_worker(cfg.sim, oc, model.spec)
        torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    try:
        while c["iteration"] < oc.rl_iterations:
            k0 = c["episodes"]
            jobs = []
            for j in range(oc.episodes_per_iter):
                k = k0 + j
                eps = oc.epsilon_start + (oc.epsilon_end - oc.epsilon_start) * min(1.0, k / oc.epsilon_decay_episodes)
                jobs.append((*pairs[k % len(pairs)], cfg.seed + 100_000 + k, eps))
            state = {k: v.detach().numpy().copy() for k, v in model.state_dict().items()}
            t_roll = time.time()
            if pool is None:
                eps_out = _run_episodes(state, jobs)
            else:
                chunks = [jobs[w::cfg.workers] for w in range(cfg.workers) if jobs[w::cfg.workers]]
                eps_out = [e for part in pool.map(_run_episodes, [state] * len(chunks), chunks) for e in part]
            for e in eps_out:
                replay.push({k: e[k] for k in TRANSITION_KEYS})
            steps = int(sum(len(e["reward"]) for e in eps_out))
            steps_per_s = steps / max(time.time() - t_roll, 1e-9)
            model.train()
            losses = [td_update(model, target, opt, replay.sample(rng, oc.batch_size), step_gamma)
                      for _ in range(oc.train_batches)]
            model.eval()
            c["episodes"] += len(eps_out)
            c["env_steps"] += steps
            c["updates"] += oc.train_batches
            c["since_target"] += len(eps_out)
            if c["since_target"] >= oc.target_update_episodes:
                target.load_state_dict(model.state_dict())
                c["since_target"] = 0
            c["iteration"] += 1
            outcomes = [e["outcome"] for e in eps_out]
            log.add("rl", c["episodes"], td_loss=float(np.mean(losses)), epsilon=jobs[-1][3],
                    success_rate=outcomes.count("success") / len(outcomes),
                    collision_rate=sum(o.startswith("collision") for o in outcomes) / len(outcomes),
                    episode_steps=steps / len(outcomes), env_steps_per_s=steps_per_s)
            if c["iteration"] % oc.checkpoint_every == 0 or c["iteration"] == oc.rl_iterations:
                c["wall_s"] = time.time() - t_start
                _save_state(rl_dir, model, target, opt, replay, c)
    finally:
        if pool is not None:
            pool.shutdown()
    c["wall_s"] = time.time() - t_start
    budget = {"expert_episodes": c["expert_episodes"], "expert_frames": c["expert_frames"],
              "il_epochs": oc.il_epochs, "rl_episodes": c["episodes"], "rl_env_steps": c["env_steps"],
              "rl_updates": c["updates"], "rendered_frames": 0, "wall_s": round(c["wall_s"], 1)}
    save_baseline(out, NAME, model, model.spec, observation_description(oc), budget,
                  config={f.name: getattr(oc, f.name) for f in fields(oc)})
    return {"budget": budget, "il_loss": c["il_loss"], "il_episodes_kept": c["il_episodes_kept"],
            "expert_success_rate": c["expert_success_rate"]}


def observation_description(oc: Config) -> dict[str, Any]:
    """``policy.json``'s ``observation_space``: the inputs and the run-time options of the lookahead."""
    return {"humans": f"perfect tracks within {oc.sensor_range_m} m, nearest {oc.max_humans}, goal frame "
                      "[px, py, vx, vy, radius, distance, radius sum] + mask",
            "self": "[d_g, v_pref, theta, radius, vx, vy] (goal frame)",
            "om": f"angular map of the static scan: {oc.om_sectors} sectors, closeness 1 - r/{oc.om_range_m} m",
            **{k: v for k, v in asdict(oc).items() if k in _RUNTIME}}
