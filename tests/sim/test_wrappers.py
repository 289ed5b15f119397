"""The wrappers that decide what a driver may know beyond its sensors (sim.wrappers)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from sim.env import CameraConfig, CrowdNavEnv, SimConfig
from sim.wrappers import FollowWaypoints, PrivilegedObservation, PrivilegedWorld, WorldView, with_privileges

SMALL = SimConfig(max_episode_s=3.0, camera=CameraConfig(width_px=64, height_px=48))


def test_privileged_world_is_a_copy_of_the_true_state():
    env = PrivilegedWorld(CrowdNavEnv(config=replace(SMALL, scene="office_lobby", density=0.2, obs_mode="state")))
    _, info = env.reset(seed=2)
    w, u = info["world"], env.unwrapped
    assert isinstance(w, WorldView) and w.crowd.n == u.crowd.n > 0
    np.testing.assert_array_equal(w.crowd.pos, u.crowd.pos)
    np.testing.assert_array_equal(w.robot, u.robot)
    assert w.d_goal == u.d_goal and w.layout is u.layout
    w.crowd.pos[:] = 0.0  # a driver scribbling on its view does not move anybody
    assert not np.array_equal(u.crowd.pos, w.crowd.pos)


def test_privileged_observation_equals_the_privileged_obs_mode():
    plain = CrowdNavEnv(config=replace(SMALL, scene="office_lobby", density=0.2, obs_mode="privileged"))
    wrapped = PrivilegedObservation(CrowdNavEnv(config=replace(SMALL, scene="office_lobby", density=0.2,
                                                               obs_mode="visual")))
    a, _ = plain.reset(seed=5)
    b, _ = wrapped.reset(seed=5)
    assert {"rgb_left", "depth_left"} <= set(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_follow_waypoints_retargets_the_state_and_reports_the_waypoint():
    cfg = replace(SMALL, scene="office_floor", density=0.0, obs_mode="privileged")
    env = FollowWaypoints(CrowdNavEnv(config=cfg), np.array([[8.0, 10.0], [27.0, 10.0]]))
    obs, info = env.reset(seed=1, options={"start": [3.0, 10.0], "goal": [27.0, 10.0]})
    u = env.unwrapped
    np.testing.assert_array_equal(info["waypoint"], [8.0, 10.0])
    np.testing.assert_array_equal(obs["state"], u.robot_state(info["waypoint"]))
    assert obs["state"][2] == pytest.approx(5.0, abs=1e-5)  # 5 m to the first waypoint, 24 m to the goal
    np.testing.assert_array_equal(obs["subgoal"], u.privileged_subgoal(info["waypoint"]))


def test_with_privileges_adds_the_world_only_for_privileged_methods():
    cfg = replace(SMALL, scene="hallway", density=0.1, obs_mode="visual")
    _, info = with_privileges(CrowdNavEnv(config=cfg), "visual").reset(seed=0)
    assert "world" not in info
    obs, info = with_privileges(CrowdNavEnv(config=cfg), "privileged").reset(seed=0)
    assert "world" in info and "peds" in obs


def test_follow_waypoints_without_waypoints_follows_the_global_planners_route():
    env = FollowWaypoints(CrowdNavEnv(scene="warehouse_routing", density=0.0, obs_mode="state", info_level="basic"))
    routed = 0
    for seed in range(6):
        obs, info = env.reset(seed=seed)
        u = env.unwrapped
        np.testing.assert_allclose(env.waypoints[-1], u.goal)
        legs = np.vstack([u.start, env.waypoints])
        assert np.sum(np.hypot(*np.diff(legs, axis=0).T)) == pytest.approx(u.shortest_path_m, rel=0.03)
        for a, b in zip(legs[:-1], legs[1:], strict=True):  # every leg of the route is free for the robot
            assert u.layout.segments_clear(a[None], b[None], u.cfg.robot.radius_m)[0]
        routed += len(env.waypoints) > 1
        np.testing.assert_array_equal(info["waypoint"], env.follower.current(u.robot[:2]))
    assert routed >= 1  # some pairs of the shelf hall need a corner
