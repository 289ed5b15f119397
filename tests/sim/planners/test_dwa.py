"""Tests of sim.planners.dwa: back-projection, costmap, obstacle memory, the controller in the env, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.core.errors import ConfigError
from sim.env import CameraConfig, CrowdNavEnv
from sim.planners.dwa import (
    DWAConfig,
    DWAController,
    build_costmap,
    rasterise_costmap,
)
from tests.sim.helpers_depth import SPECS, wall_depth


def empty_env(scene: str, density: float = 0.0, **kw) -> CrowdNavEnv:
    kw.setdefault("camera", CameraConfig(width_px=64, height_px=48))
    return CrowdNavEnv(scene=scene, density=density, obs_mode="state", info_level="basic", **kw)


def place(env: CrowdNavEnv, pose, goal, velocity=(0.0, 0.0)) -> None:
    """Put the robot and goal where a test wants them (after ``reset``)."""
    env.robot = np.array(pose, dtype=np.float64)
    env.goal = np.array(goal, dtype=np.float64)
    env.robot_v = np.array(velocity, dtype=np.float64)
    env.d_goal = float(np.hypot(*(env.goal - env.robot[:2])))


def drive(env: CrowdNavEnv, dwa: DWAController, max_steps: int):
    """Run the DWA until the episode ends or ``max_steps``.

    Returns:
        ``(outcome, poses, commands, smallest static clearance)``; outcome is None if the episode did not end.
    """
    poses, cmds, min_static = [env.robot.copy()], [], math.inf
    outcome = None
    for _ in range(max_steps):
        v, w = dwa.command(env)
        _, _, terminated, truncated, info = env.step(env.encode_command(v, w))
        poses.append(env.robot.copy())
        cmds.append((v, w))
        min_static = min(min_static, env.d_static)
        if terminated or truncated:
            outcome = info["outcome"]
            break
    return outcome, np.array(poses), np.array(cmds), min_static


# ------------------------------------------------------------------------------------------------- perception


@pytest.mark.parametrize("wall_x", [1.5, 3.0])
def test_costmap_of_a_flat_wall_puts_occupied_cells_at_its_distance(wall_x):
    cfg = DWAConfig(pixel_stride=1)
    depths = [wall_depth(s, wall_x) for s in SPECS]
    cm = build_costmap(depths, SPECS, (0.0, 0.0, 0.0), cfg, robot_radius_m=0.3)
    ii, jj = np.nonzero(cm.occupied)
    x = cm.origin[0] + jj * cm.res_m
    y = cm.origin[1] + ii * cm.res_m
    assert len(x) > 20
    # every occupied cell is on the wall (the floor seen in front of it is outside the height band)
    assert np.all(np.abs(x - wall_x) <= cm.res_m / 2 + 1e-9), np.unique(x)
    # the wall is seen across both cameras' views, seam included
    assert y.min() < -wall_x * 0.9 and y.max() > wall_x * 0.9
    assert np.any(np.abs(y) < cm.res_m)
    assert float(cm.lookup(np.zeros(2))) == pytest.approx(wall_x, abs=cm.res_m)
    assert cm.inflation_m == pytest.approx(0.3 + cfg.safety_margin_m)
    free_ahead = cm.lookup(np.stack([np.linspace(0, wall_x - cm.inflation_m - 0.1, 20), np.zeros(20)], -1))
    assert np.all(free_ahead >= cm.inflation_m)


def test_floor_and_high_points_are_not_obstacles():
    depths = [wall_depth(s, None, floor=True) for s in SPECS]  # only the floor is in view
    assert all((d > 0).any() for d in depths)
    cm = build_costmap(depths, SPECS, (0.0, 0.0, 0.0), DWAConfig(pixel_stride=1), robot_radius_m=0.3)
    assert not cm.occupied.any()
    pts = np.array([[1.0, 0.0, 0.01], [1.0, 0.0, 1.0], [1.0, 0.0, 2.5]])
    cm2 = rasterise_costmap(pts[1:2, :2], 8.0, 0.1, 0.4)
    assert cm2.n_points == 1


def test_costmap_is_robot_centred_and_aligned():
    # an obstacle point 2 m ahead of a robot at (5, 5) facing +y lies at world (5, 7)
    cfg = DWAConfig()
    mem = np.array([[5.0, 7.0, 1.0]])
    empty = [np.zeros((s.height_px, s.width_px), np.float32) for s in SPECS]
    cm = build_costmap(empty, SPECS, (5.0, 5.0, math.pi / 2), cfg, 0.3, memory_xyz=mem)
    ii, jj = np.nonzero(cm.occupied)
    assert len(ii) == 1
    assert cm.origin[0] + jj[0] * cm.res_m == pytest.approx(2.0, abs=cm.res_m / 2)
    assert cm.origin[1] + ii[0] * cm.res_m == pytest.approx(0.0, abs=cm.res_m / 2)




def test_controller_remembers_an_obstacle_that_left_the_view():
    env = empty_env("open_crowd")
    env.reset(seed=0)
    dwa = DWAController(DWAConfig(memory_s=1.0, pixel_stride=1))
    dwa.reset(env)
    seen = [wall_depth(s, 2.0, floor=False) for s in SPECS]
    blank = [np.zeros_like(d) for d in seen]
    pose = np.array([0.0, 0.0, 0.0])
    dwa.command_from(seen, pose, 0.0, 0.0, waypoint_xy=(5.0, 0.0))
    assert dwa.last_costmap.occupied.any()
    for _ in range(5):  # 0.5 s of seeing nothing (cameras covered): the wall is remembered
        dwa.command_from(blank, pose, 0.0, 0.0, waypoint_xy=(5.0, 0.0))
    assert float(dwa.last_costmap.lookup(np.zeros(2))) == pytest.approx(2.0, abs=0.1)
    for _ in range(6):  # past memory_s: forgotten
        dwa.command_from(blank, pose, 0.0, 0.0, waypoint_xy=(5.0, 0.0))
    assert not dwa.last_costmap.occupied.any()


# ------------------------------------------------------------------------------------------------- controller
def test_dwa_reaches_the_goal_in_an_empty_room():
    env = empty_env("open_crowd")
    env.reset(seed=0)
    assert env.crowd.n == 0
    place(env, (1.5, 6.0, 0.3), (10.5, 6.0))  # between the pillar rows
    dwa = DWAController()
    dwa.reset(env)
    outcome, poses, cmds, min_static = drive(env, dwa, 250)
    assert outcome == "success", (outcome, poses[-1])
    assert len(cmds) * env.cfg.dt_s < 15.0  # 9 m at up to 1 m/s
    assert cmds[:, 0].max() > 0.9  # it speeds up where nothing is in the way
    # the window limits acceleration
    dv = np.diff(np.concatenate([[0.0], cmds[:, 0]]))
    assert dv.max() <= DWAConfig().acc_v_mps2 * env.cfg.dt_s + 1e-6  # (actions are float32)


def test_dwa_goes_around_a_pillar_in_the_way():
    env = empty_env("open_crowd")
    env.reset(seed=0)
    place(env, (1.0, 3.0, 0.0), (6.0, 3.0))  # the pillar at (3, 3), radius 0.3, blocks the straight line
    dwa = DWAController()
    dwa.reset(env)
    outcome, poses, _, min_static = drive(env, dwa, 300)
    assert outcome == "success", (outcome, poses[-1])
    assert min_static > env.cfg.robot.radius_m + 0.05
    assert np.abs(poses[:, 1] - 3.0).max() > 0.5  # it went around


def test_dwa_stops_before_a_wall_when_the_goal_is_behind_it():
    env = empty_env("hallway", max_episode_s=8.0)
    env.reset(seed=0)
    # 1.5 m from the north wall of the 3 m hallway, driving at it at full speed; the goal is behind the wall
    place(env, (7.0, 1.5, math.pi / 2), (7.0, 8.0), velocity=(1.0, 0.0))
    dwa = DWAController()
    dwa.reset(env)
    outcome, poses, cmds, min_static = drive(env, dwa, 80)
    assert outcome == "timeout"  # never a collision
    assert min_static > env.cfg.robot.radius_m + 0.05
    assert poses[:, 1].max() < 3.0 - env.cfg.robot.radius_m - 0.05
    assert np.abs(cmds[-10:, 0]).max() < 0.05  # it ends standing (or turning on the spot)
    # it braked as soon as the wall was within its stopping distance, not at the last moment
    assert cmds[:5, 0].max() <= 1.0 and cmds[10:, 0].max() < 0.6


def test_dwa_follows_an_external_waypoint():
    env = empty_env("open_crowd")
    env.reset(seed=0)
    place(env, (6.0, 6.0, 0.0), (11.0, 6.0))
    dwa = DWAController()
    dwa.reset(env)
    for _ in range(30):
        v, w = dwa.command(env, waypoint_xy=(6.0, 11.0))  # to the left of the robot
        env.step(env.encode_command(v, w))
    assert env.robot[1] > 6.5 and abs(env.robot[2] - math.pi / 2) < 0.6


def test_command_before_reset_raises():
    env = empty_env("open_crowd")
    env.reset(seed=0)
    with pytest.raises(RuntimeError, match="reset"):
        DWAController().command(env)


@pytest.mark.parametrize("field, value", [
    ("n_v", 1), ("n_omega", 2.5), ("acc_v_mps2", 0.0), ("arc_step_m", -0.1), ("memory_s", -1.0),
    ("min_height_m", 2.0), ("w_velocity", float("nan")), ("pixel_stride", True), ("costmap_size_m", 0.2),
    ("arc_step_m", 5.0),
])
def test_bad_config_names_the_field(field, value):
    cfg = DWAConfig(**{field: value})
    with pytest.raises(ConfigError, match=f"dwa.{field}"):
        cfg.validate()
    with pytest.raises(ConfigError, match=f"dwa.{field}"):
        DWAController(cfg)


def test_all_weights_zero_is_rejected():
    with pytest.raises(ConfigError, match="weights"):
        DWAConfig(w_heading=0.0, w_dist=0.0, w_velocity=0.0).validate()
