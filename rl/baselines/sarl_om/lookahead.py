"""SARL*-OM's policy (package docstring): the one-step lookahead over the robot's action grid with the value
network."""

from __future__ import annotations

import math

import numpy as np
import torch

from rl.baselines.sarl_om.configuration import Config
from rl.baselines.sarl_om.model import SarlOMValue, to_tensors
from rl.baselines.sarl_om.observation import Scene, joint_state
from rl.baselines.sarl_om.rewards import reward
from sim.env import CrowdNavEnv
from sim.robot import action_grid


class Lookahead:
    """SARL's one-step lookahead over the action grid (package docstring): each action is held for
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
            v = self.model(*to_tensors(nxt)).numpy().astype(np.float64)
        return r + self.oc.gamma ** (self.times[-1] * sc.v_pref) * np.where(done, 0.0, v)

    def act(self, sc: Scene, epsilon: float = 0.0, rng: np.random.Generator | None = None) -> int:
        """The argmax action index (uniformly random with probability ``epsilon``)."""
        if epsilon > 0 and rng is not None and rng.random() < epsilon:
            return int(rng.integers(len(self.grid)))
        return int(np.argmax(self.values(sc)))
