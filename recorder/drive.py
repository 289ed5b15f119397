"""Drive an episode and yield what the recorder logs: :class:`recorder.schema.EpisodeMeta` then frames."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from pipeline.core.errors import ConfigError
from recorder.schema import EpisodeMeta, Frame, episode_meta_from_env, frame_from_env
from sim.env import CrowdNavEnv, SimConfig
from sim.episode import Driver, episode_steps
from sim.expert import ExpertDriver
from sim.wrappers import PrivilegedWorld

DRIVERS = ("expert",)


@dataclass
class Episode:
    """A driven episode: its metadata, its static occupancy grid and a lazy iterator of its frames.

    ``occupancy`` is ``H x W`` bool (True = obstacle), row ``i`` along +y and column ``j`` along +x from
    ``meta.occupancy_origin_xy`` at ``meta.occupancy_resolution_m``.
    """

    meta: EpisodeMeta
    occupancy: np.ndarray
    frames: Iterator[Frame]


def drive_episode(sim_cfg: SimConfig, seed: int, driver: str | Driver = "expert") -> Episode:
    """Reset a visual-mode env with ``seed`` and return the :class:`Episode` (frames are produced lazily).

    The iterator yields the reset frame (step 0) and one frame per step until the episode ends; the env is
    closed when it is exhausted. ``driver``: ``"expert"`` (the privileged expert; policies are recorded by their
    own stages) or any :class:`sim.episode.Driver` object (recorded under its class name; it sees the privileged
    world like the expert).
    """
    if isinstance(driver, str) and driver not in DRIVERS:
        raise ConfigError(f"driver: expected one of {list(DRIVERS)} or a Driver object, got {driver!r}")
    env = CrowdNavEnv(config=replace(sim_cfg, obs_mode="visual", info_level="full"))
    steps = episode_steps(PrivilegedWorld(env), ExpertDriver() if isinstance(driver, str) else driver, seed)
    first = next(steps)  # the reset
    meta = episode_meta_from_env(env, seed, driver if isinstance(driver, str) else type(driver).__name__)

    def frames() -> Iterator[Frame]:
        try:
            yield frame_from_env(env, first.obs, first.info, 0)
            for tr in steps:
                yield frame_from_env(env, tr.obs, tr.info, tr.step, command=tuple(env.robot_v), reward=tr.reward,
                                     done=tr.done)
        finally:
            env.close()

    return Episode(meta, env.layout.occupancy.copy(), frames())
