"""The one episode loop and the Driver protocol (sim.episode), the action codec, the expert as a driver."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from sim.env import CameraConfig, CrowdNavEnv, SimConfig
from sim.episode import Transition, episode_steps, run_episode
from sim.expert import ExpertDriver, run_expert_episode
from sim.robot import ActionCodec, RobotConfig

SMALL = SimConfig(max_episode_s=3.0, camera=CameraConfig(width_px=64, height_px=48))


class Recorder:
    """A driver that turns on the spot and keeps what it was given."""

    def __init__(self) -> None:
        self.reset_info: dict = {}
        self.seen: list[tuple[dict, dict]] = []

    def reset(self, obs, info) -> None:
        self.reset_info = info
        self.codec = info["action_codec"]

    def act(self, obs, info):
        self.seen.append((obs, info))
        return self.codec.encode(0.0, 1.0)


def test_the_loop_yields_the_reset_then_every_step_until_the_end():
    env = CrowdNavEnv(config=replace(SMALL, scene="hallway", density=0.1, obs_mode="state"))
    driver = Recorder()
    steps = list(episode_steps(env, driver, seed=3))
    assert steps[0].step == 0 and steps[0].action is None and not steps[0].done
    assert [t.step for t in steps] == list(range(len(steps)))
    assert steps[-1].done and not any(t.done for t in steps[:-1])
    assert steps[-1].truncated and not steps[-1].terminated  # turning on the spot: the time limit ends it
    assert len(driver.seen) == len(steps) - 1  # one act per step, none after the end
    for k, (obs, _) in enumerate(driver.seen):
        assert obs is steps[k].obs  # each act sees the observation that the step before returned
    assert env.unwrapped.trace().n_steps == len(steps) - 1


def test_reset_info_carries_what_a_driver_needs_and_no_env():
    env = CrowdNavEnv(config=replace(SMALL, scene="hallway", density=0.1, obs_mode="visual"))
    driver = Recorder()
    tr = next(episode_steps(env, driver, seed=1))
    info = driver.reset_info
    assert info is tr.info
    assert [c.name for c in info["cameras"]] == ["left", "right"]
    assert isinstance(info["action_codec"], ActionCodec) and info["config"] is env.cfg
    np.testing.assert_array_equal(info["goal_xy"], env.goal)
    np.testing.assert_array_equal(info["odom"], env.robot)
    assert "world" not in info and "waypoint" not in info  # only wrappers add those
    assert not any(isinstance(v, CrowdNavEnv) for v in info.values())


def test_action_codec_round_trips_the_grid_and_clips():
    robot = RobotConfig()
    d = ActionCodec("discrete", robot)
    for k in (0, 7, len(d.grid) - 1):
        assert d.encode(*d.decode(k)) == k
    c = ActionCodec("continuous", robot)
    assert c.decode(c.encode(0.5, -1.0)) == pytest.approx((0.5, -1.0))
    assert c.decode(c.encode(9.0, 9.0)) == pytest.approx((robot.v_max_mps, robot.omega_max_radps))


def test_expert_driver_needs_the_privileged_world():
    env = CrowdNavEnv(config=replace(SMALL, scene="hallway", density=0.1, obs_mode="state"))
    with pytest.raises(KeyError, match="world"):
        run_episode(env, ExpertDriver(), seed=0, method="expert")
    trace = run_expert_episode(env, seed=0)  # wraps it in PrivilegedWorld
    assert trace.n_steps > 0 and isinstance(Transition(0, {}, {}).done, bool)
