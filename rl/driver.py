"""Saved policies as :class:`sim.episode.Driver` s, and the per-process cache of loaded weights.

A teacher acts on the privileged observation (its env is in ``obs_mode="privileged"`` or wrapped in
:class:`sim.wrappers.PrivilegedObservation`); a student on the rendered observation through its frozen encoder
(:class:`rl.observe.StudentObserver`, built from the cameras and config the env reports at reset). A long-horizon
waypoint reaches both through the observation (:class:`sim.wrappers.FollowWaypoints` re-targets the state s).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rl.lookahead import ObstacleShield
from rl.networks import MLP_HEADS
from rl.observe import (
    StudentObserver,
    load_student_encoder,
    load_student_forecaster,
    load_student_heads,
    observer_for,
)
from rl.policy import POLICY_WEIGHTS, act, action_logits, load_policy, read_policy_json

_CACHE: dict[str, Any] = {}
SAMPLE_SEED_KEY = 7_919  # mixed with the episode seed: the sampling stream differs from the env's own


def process_cached(key: str, make: Callable[[], Any]) -> Any:
    """``make()`` once per process and ``key`` (weights loaded once per worker of a process pool)."""
    if key not in _CACHE:
        _CACHE[key] = make()
    return _CACHE[key]


def cached_policy(path: Path | None, shield_s: float | None = None):
    """The policy saved in ``path`` (None for None), loaded once per process, file version and ``shield_s``
    (:func:`rl.policy.load_policy`)."""
    if path is None:
        return None
    weights = Path(path) / POLICY_WEIGHTS
    if not weights.is_file():  # not cached: load_policy names what is missing
        return load_policy(path, shield_s)[0]
    return process_cached(f"policy:{path}:{os.path.getmtime(weights)}:{shield_s}",
                          lambda: load_policy(path, shield_s)[0])


def cached_student_encoder(variant: str, encoder_ckpt: Path | str | None, device: str = "cpu",
                           precision: str = "fp32"):
    """The frozen encoder of a student variant (:func:`rl.observe.load_student_encoder`) on ``device`` at
    ``precision``, once per process."""
    return process_cached(f"enc:{variant}:{encoder_ckpt}:{device}:{precision}",
                          lambda: load_student_encoder(variant, encoder_ckpt, device, precision))


def cached_student_heads(variant: str, head: str, map_cost: bool, encoder_ckpt: Path | str | None, encoder):
    """The frozen pretext heads a student's lookahead head reads the BEV's occupancy with
    (:func:`rl.observe.load_student_heads`; None when it reads none), once per process."""
    return process_cached(f"heads:{variant}:{head}:{map_cost}:{encoder_ckpt}",
                          lambda: load_student_heads(variant, head, map_cost, encoder_ckpt, encoder))


def cached_student_forecaster(variant: str, head: str, intention_ckpt: Path | str | None):
    """The frozen intention model of a student (:func:`rl.observe.load_student_forecaster`; None when it has
    none), once per process."""
    return process_cached(f"intent:{variant}:{head}:{intention_ckpt}",
                          lambda: load_student_forecaster(variant, head, intention_ckpt))


def mlp_shield(sim_cfg, shield_s: float) -> ObstacleShield | None:
    """The obstacle shield of an MLP-head student over ``shield_s`` (None when 0) for the env of ``sim_cfg`` (its
    robot, control period and scan layout)."""
    if not shield_s:
        return None
    return ObstacleShield(sim_cfg.robot, sim_cfg.dt_s, sim_cfg.scan_rays, sim_cfg.scan_range_m, shield_s)


def observer_head(head: str, scan: bool) -> str:
    """The perception a student's observer runs: its head's, or for an MLP head (``mlp``, ``mlp_intention``) whose
    shield or replay reads the depth scan (``scan``) the lookahead head's (its scan, without the detected people's
    points; its tracks and forecasts are the ``mlp_intention`` head's too)."""
    return "lookahead" if head in MLP_HEADS and scan else head


def shielded_logits(policy, obs: dict[str, np.ndarray], shield: ObstacleShield | None) -> np.ndarray:
    """The policy's action logits on ``obs`` (float64) less ``shield``'s penalty on its perceived ``scan``."""
    z = action_logits(policy, obs).astype(np.float64)
    if shield is not None:
        z = z - shield(torch.as_tensor(obs["scan"], dtype=torch.float32)[None])[0].double().numpy()
    return z


class PolicyDriver:
    """A saved teacher or student policy (``policy.json`` kind ``teacher`` | ``student``) as a driver."""

    def __init__(self, ckpt: Path, shield_s: float | None = None, sample_tau: float | None = None,
                 encoder_precision: str | None = None) -> None:
        """``shield_s``: the obstacle shield's horizon instead of the saved one (None = as saved; 0 = off): inside a
        lookahead head (:func:`rl.policy.load_policy`), or for a student with the MLP head an
        :class:`rl.lookahead.ObstacleShield` on its logits, on the depth scan its observer then also perceives.
        ``sample_tau``: pick each action by sampling softmax(logits / τ) with a generator seeded by the episode's
        seed at reset (reproducible per episode), instead of the argmax (None). ``encoder_precision``: a student's
        frozen encoder at this precision instead of the one its policy.json names (None)."""
        torch.set_num_threads(1)
        self.sample_tau = sample_tau
        self.rng = np.random.default_rng(0)
        self.policy = cached_policy(ckpt, shield_s)
        self.desc = read_policy_json(ckpt)
        self.student = self.desc["kind"] == "student"
        self.encoder = (cached_student_encoder(self.desc["variant"], self.desc.get("encoder"),
                                               precision=encoder_precision or self.desc.get("encoder_precision",
                                                                                            "fp32"))
                        if self.student else None)
        self.head = self.desc.get("net", {}).get("head", "mlp")
        self.forecaster = (cached_student_forecaster(self.desc["variant"], self.head, self.desc.get("intention"))
                           if self.student else None)
        self.map_cost = bool(self.desc.get("net", {}).get("map_cost", False))
        self.map_heads = (cached_student_heads(self.desc["variant"], self.head, self.map_cost, self.desc.get("encoder"),
                                               self.encoder) if self.student else None)
        # the MLP head's obstacle shield (built at the first reset, from the env's robot, control period and scan)
        saved = self.desc.get("net", {}).get("shield_s", 0.0)
        self.mlp_shield_s = (float(saved if shield_s is None else shield_s)
                             if self.student and self.head == "mlp" else 0.0)
        self.shield: ObstacleShield | None = None
        # an MLP-head student's observer also perceives the depth scan its shield would read, without acting on it
        # (evaluation.failures --replay reads what it showed); takes effect at the next reset
        self.perceive_scan = False
        self.observer: StudentObserver | None = None
        self._observer_head: str | None = None
        self.last_obs: dict[str, np.ndarray] | None = None

    def reset(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        self.rng = np.random.default_rng([SAMPLE_SEED_KEY, int(info.get("episode_seed", 0))])
        if self.student:
            perception = observer_head(self.head, bool(self.mlp_shield_s) or self.perceive_scan)
            if self.observer is None or perception != self._observer_head:
                cfg = info["config"]
                self.shield = mlp_shield(cfg, self.mlp_shield_s)
                self.observer = observer_for(info["cameras"], cfg, self.desc["variant"], self.encoder, perception,
                                             forecaster=self.forecaster, map_cost=self.map_cost,
                                             map_heads=self.map_heads,
                                             track_unseen_s=self.desc.get("net", {}).get("track_unseen_s", 0.0))
                self._observer_head = perception
            self.observer.reset()

    def act(self, obs: dict[str, np.ndarray], info: dict[str, Any]):
        o = self.observer(obs) if self.student else dict(obs)
        o["state"] = obs["state"]
        self.last_obs = o
        if self.sample_tau is None and self.shield is None:
            return act(self.policy, o)
        z = shielded_logits(self.policy, o, self.shield)
        if self.sample_tau is None:
            return int(np.argmax(z))
        z = z / self.sample_tau
        p = np.exp(z - z.max())
        return int(self.rng.choice(len(p), p=p / p.sum()))

    def bev_panel(self) -> np.ndarray | None:
        """An ``H x W`` map of what the policy's BEV input held at the last step (videos), or None."""
        o = self.last_obs or {}
        if "bev" in o:
            return np.linalg.norm(o["bev"], axis=0)
        if "occ" in o:
            return o["occ"][0]
        return None
