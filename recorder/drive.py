"""Drive an episode and yield what the recorder logs: :class:`recorder.schema.EpisodeMeta` then frames."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from recorder.schema import EpisodeMeta, Frame, episode_meta_from_env, frame_from_env
from sim.env import CrowdNavEnv, SimConfig
from sim.expert import expert_steps

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


def drive_episode(sim_cfg: SimConfig, seed: int, driver: str = "expert") -> Episode:
    """Reset a visual-mode env with ``seed`` and return the :class:`Episode` (frames are produced lazily).

    The iterator yields the reset frame (step 0) and one frame per step until the episode ends; the env is
    closed when it is exhausted. Only the privileged ``expert`` driver exists so far (policies come with train).
    """
    if driver not in DRIVERS:
        from pipeline.core.errors import ConfigError

        raise ConfigError(f"driver: expected one of {list(DRIVERS)}, got {driver!r}")
    env = CrowdNavEnv(config=replace(sim_cfg, obs_mode="visual", info_level="full"))
    steps = expert_steps(env, seed)
    obs, info, _ = next(steps)  # the reset
    meta = episode_meta_from_env(env, seed, driver)

    def frames() -> Iterator[Frame]:
        try:
            yield frame_from_env(env, obs, info, 0)
            for step, (o, inf, (r, done)) in enumerate(steps, start=1):
                yield frame_from_env(env, o, inf, step, command=tuple(env.robot_v), reward=r, done=done)
        finally:
            env.close()

    return Episode(meta, env.layout.occupancy.copy(), frames())
