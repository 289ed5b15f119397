"""The one episode loop and the Driver protocol every method implements.

A driver is fed only what the env returns::

    driver.reset(obs, info)          # after env.reset: info carries the episode's fixed facts (cameras,
                                     # action_codec, goal_xy, occupancy; see sim.env)
    action = driver.act(obs, info)   # an action of the env's action space

What a method may not observe stays out of its reach: privileged state comes through
:class:`sim.wrappers.PrivilegedWorld` (``info["world"]``), a long-horizon waypoint through
:class:`sim.wrappers.FollowWaypoints` (``info["waypoint"]``, and ``obs`` re-targeted to it), each added only for
the methods that get it. :func:`episode_steps` is the loop; record, rollout, DAgger, acceptance and the benchmark
all drive episodes through it and differ only in what they do with each :class:`Transition`.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Protocol

import gymnasium as gym
import numpy as np

from sim.trace import EpisodeTrace


class Driver(Protocol):
    """Drives one episode at a time from what the env returns (see the module docstring)."""

    def reset(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None: ...

    def act(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> Any: ...


@dataclass
class Transition:
    """One point of an episode: ``step`` 0 is the reset (``action``/``reward`` None, flags False); step ``t``
    is what ``env.step(action)`` returned for the action chosen on step ``t - 1``'s observation."""

    step: int
    obs: dict[str, np.ndarray]
    info: dict[str, Any]
    action: Any = None
    reward: float | None = None
    terminated: bool = False  # the goal or a collision (no bootstrapping past it)
    truncated: bool = False  # the time limit

    @property
    def done(self) -> bool:
        return self.terminated or self.truncated


def episode_steps(env: gym.Env, driver: Driver, seed: int, options: dict | None = None) -> Iterator[Transition]:
    """Resets ``env`` with ``seed`` (and ``options``), lets ``driver`` act until the episode ends, and yields every
    :class:`Transition` (the reset first). The env stays open: the caller closes it."""
    obs, info = env.reset(seed=seed, options=options)
    driver.reset(obs, info)
    yield Transition(0, obs, info)
    step = 0
    while True:
        action = driver.act(obs, info)
        obs, reward, terminated, truncated, info = env.step(action)
        step += 1
        yield Transition(step, obs, info, action, float(reward), bool(terminated), bool(truncated))
        if terminated or truncated:
            return


def run_episode(env: gym.Env, driver: Driver, seed: int, method: str, options: dict | None = None,
                on_step=None) -> EpisodeTrace:
    """Drives one episode (:func:`episode_steps`) and returns its :class:`sim.trace.EpisodeTrace`.

    Args:
        on_step: optional ``callback(transition)`` for every transition, the reset included.
    """
    for tr in episode_steps(env, driver, seed, options):
        if on_step is not None:
            on_step(tr)
    return env.unwrapped.trace(method=method)
