"""Tests of sim.env: the gymnasium API, determinism, actions, observations, termination, info, traces, errors."""

from __future__ import annotations

import math

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import sim
from pipeline.core.errors import ConfigError
from sim.crowd import CrowdConfig
from sim.env import CameraConfig, CrowdNavEnv, SimConfig
from sim.expert import PrivilegedExpert
from sim.robot import RobotConfig, action_grid
from sim.scene import load_scene

SMALL_CAM = SimConfig(camera=CameraConfig(width_px=64, height_px=48))


def state_env(scene="office_lobby", density=0.1, **kw) -> CrowdNavEnv:
    kw.setdefault("obs_mode", "state")
    kw.setdefault("info_level", "basic")
    return CrowdNavEnv(scene=scene, density=density, **kw)


MODES = [pytest.param(dict(obs_mode="visual", config=SMALL_CAM), id="visual"),
         pytest.param(dict(obs_mode="visual", config=SMALL_CAM, detect_poses=False), id="visual-no-poses"),
         pytest.param(dict(obs_mode="privileged"), id="privileged"),
         pytest.param(dict(obs_mode="state"), id="state")]


# ------------------------------------------------------------------------------------------------ gymnasium
@pytest.mark.filterwarnings("ignore:.*render modes.*")
@pytest.mark.parametrize("action_type", ["continuous", "discrete"])
@pytest.mark.parametrize("kw", MODES)
def test_check_env(kw, action_type):
    env = CrowdNavEnv(scene="office_lobby", density=0.1, action_type=action_type, **kw)
    check_env(env)


def test_reset_info_occupancy_is_a_copy():
    env = state_env()
    _, info = env.reset(seed=0)
    grid = info["occupancy"]["grid"]
    before = env.layout.occupancy.copy()
    grid[:] = ~grid
    np.testing.assert_array_equal(env.layout.occupancy, before)


def test_gymnasium_make_after_import_sim():
    assert sim.ENV_ID == "icrowdnav/CrowdNav-v0" and sim.ENV_ID in gymnasium.registry
    env = gymnasium.make("icrowdnav/CrowdNav-v0", scene="office_lobby", density=0.1)
    obs, info = env.reset(seed=0)
    assert set(obs) == {"state", "odom", "rgb_left", "rgb_right", "depth_left", "depth_right", "poses",
                        "pose_mask"}
    assert obs["rgb_left"].shape == (120, 160, 3) and obs["depth_right"].shape == (120, 160)
    assert obs["poses"].shape == (6, 17, 3) and obs["pose_mask"].shape == (6, 17)
    assert env.observation_space.contains(obs)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(obs)
    assert isinstance(reward, float)
    assert env.unwrapped.crowd.n == 9
    env.close()


# --------------------------------------------------------------------------------------------- determinism
def run_episode(env, seed, actions, images=False):
    obs, _ = env.reset(seed=seed)
    poses, peds, imgs, rewards = [env.robot.copy()], [env.crowd.pos.copy()], [], []
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        poses.append(env.robot.copy())
        peds.append(env.crowd.pos.copy())
        rewards.append(r)
        if images:
            imgs.append({k: obs[k].copy() for k in ("rgb_left", "rgb_right", "depth_left", "depth_right",
                                                   "poses", "pose_mask") if k in obs})
        if term or trunc:
            break
    return np.array(poses), np.array(peds), imgs, rewards


def test_same_seed_same_trajectory_and_images_other_seed_differs():
    cfg = SimConfig(camera=CameraConfig(width_px=96, height_px=72))
    actions = list(np.random.default_rng(0).uniform(-1, 1, (20, 2)).astype(np.float32))
    actions = [np.array([0.2 + 0.8 * abs(a[0]), 0.5 * a[1]], np.float32) for a in actions]
    env_a = CrowdNavEnv(scene="office_lobby", density=0.15, obs_mode="visual", config=cfg)
    env_b = CrowdNavEnv(scene="office_lobby", density=0.15, obs_mode="visual", config=cfg)
    a = run_episode(env_a, 11, actions, images=True)
    other = run_episode(env_b, 12, actions[:5], images=True)  # env_b runs another episode first
    b = run_episode(env_b, 11, actions, images=True)
    assert len(a[0]) == len(b[0]) >= 10
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert a[3] == b[3]
    for fa, fb in zip(a[2], b[2], strict=True):
        for k in fa:
            assert fa[k].tobytes() == fb[k].tobytes(), k
    assert any(fa["pose_mask"].any() for fa in a[2])  # people were in view
    assert not np.allclose(a[0][0], other[0][0])
    assert a[2][0]["rgb_left"].tobytes() != other[2][0]["rgb_left"].tobytes()
    env_a.close()
    env_b.close()


def test_visual_mode_without_the_detector_gives_the_same_images_and_no_poses():
    actions = [np.array([0.6, 0.1 * k - 0.5], np.float32) for k in range(12)]
    a = run_episode(CrowdNavEnv(scene="office_lobby", density=0.2, obs_mode="visual", config=SMALL_CAM), 4, actions,
                    images=True)
    env = CrowdNavEnv(scene="office_lobby", density=0.2, obs_mode="visual", config=SMALL_CAM, detect_poses=False)
    b = run_episode(env, 4, actions, images=True)
    assert env.last_detections is None and "poses" not in env.observation_space.spaces
    np.testing.assert_array_equal(a[0], b[0])
    for fa, fb in zip(a[2], b[2], strict=True):
        assert set(fa) - set(fb) == {"poses", "pose_mask"}
        for k in fb:
            assert fa[k].tobytes() == fb[k].tobytes(), k


def test_state_mode_is_deterministic_and_matches_visual_mode_dynamics():
    actions = [np.array([0.6, 0.1 * k - 0.5], np.float32) for k in range(15)]
    a = run_episode(state_env(density=0.2), 4, actions)
    b = run_episode(state_env(density=0.2), 4, actions)
    v = run_episode(CrowdNavEnv(scene="office_lobby", density=0.2, obs_mode="visual", config=SMALL_CAM), 4, actions)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    # rendering does not touch the dynamics' random streams
    np.testing.assert_array_equal(a[0], v[0])
    np.testing.assert_array_equal(a[1], v[1])


def test_reset_without_seed_continues_the_stream():
    env = state_env()
    env.reset(seed=5)
    s1 = env.start.copy()
    env.reset()
    s2 = env.start.copy()
    env.reset(seed=5)
    np.testing.assert_array_equal(env.start, s1)
    assert not np.allclose(s1, s2)


# ------------------------------------------------------------------------------------------------- actions
def test_continuous_encode_decode_round_trip():
    env = state_env()
    assert env.action_space == gymnasium.spaces.Box(-1.0, 1.0, (2,), np.float32)
    for v in np.linspace(0.0, 1.0, 7):
        for w in np.linspace(-2.0, 2.0, 9):
            a = env.encode_command(v, w)
            assert a.dtype == np.float32 and env.action_space.contains(a)
            dv, dw = env.decode_action(a)
            assert dv == pytest.approx(v, abs=1e-6) and dw == pytest.approx(w, abs=1e-6)
    # out-of-range commands and actions are clipped to the limits
    np.testing.assert_allclose(env.encode_command(5.0, -9.0), [1.0, -1.0])
    assert env.decode_action(np.array([3.0, -3.0])) == (1.0, -2.0)
    assert env.decode_action(np.array([-1.0, 0.0])) == (0.0, 0.0)


def test_discrete_encode_decode_nearest_grid_cell():
    env = state_env(action_type="discrete")
    grid = action_grid(RobotConfig())
    assert env.action_space == gymnasium.spaces.Discrete(105) and grid.shape == (105, 2)
    np.testing.assert_allclose(np.unique(grid[:, 0]), [0.0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(np.unique(grid[:, 1]), np.linspace(-2, 2, 21))
    for k in range(len(grid)):
        assert env.encode_command(*env.decode_action(k)) == k
    rng = np.random.default_rng(0)
    for v, w in zip(rng.uniform(0, 1, 200), rng.uniform(-2, 2, 200), strict=True):
        k = env.encode_command(v, w)
        dv, dw = env.decode_action(k)
        d = np.hypot((grid[:, 0] - v) / 1.0, (grid[:, 1] - w) / 2.0)
        assert math.hypot(dv - v, (dw - w) / 2.0) == pytest.approx(d.min())
        assert abs(dv - v) <= 0.125 + 1e-9 and abs(dw - w) <= 0.1 + 1e-9


def test_robot_moves_by_unicycle_kinematics():
    env = state_env(density=0.0)
    env.reset(seed=1)
    x, y, yaw = env.robot
    env.step(env.encode_command(0.5, 0.0))
    np.testing.assert_allclose(env.robot, [x + 0.05 * math.cos(yaw), y + 0.05 * math.sin(yaw), yaw], atol=1e-6)
    x, y, yaw = env.robot
    v, w = env.decode_action(env.encode_command(1.0, 1.0))
    env.step(env.encode_command(1.0, 1.0))
    r = v / w
    np.testing.assert_allclose(env.robot[:2], [x + r * (math.sin(yaw + 0.1 * w) - math.sin(yaw)),
                                               y - r * (math.cos(yaw + 0.1 * w) - math.cos(yaw))], atol=1e-6)


# -------------------------------------------------------------------------------------------- observations
def test_state_and_privileged_observations():
    env = CrowdNavEnv(scene="office_lobby", density=0.2, obs_mode="privileged", privileged_peds=5)
    obs, info = env.reset(seed=3)
    for _ in range(3):
        obs, *_ , info = env.step(env.encode_command(0.7, 0.3))
    x, y, yaw = env.robot
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = env.goal - env.robot[:2]
    np.testing.assert_allclose(obs["state"], [c * dx + s * dy, -s * dx + c * dy, math.hypot(dx, dy), 0.7, 0.0],
                               atol=1e-5)
    np.testing.assert_allclose(obs["odom"], env.robot, atol=1e-5)
    peds = obs["peds"]
    assert peds.shape == (5, 6) and (peds[:, 5] == 1).all()
    d = np.hypot(peds[:, 0], peds[:, 1])
    assert np.all(np.diff(d) >= 0)
    true_d = np.sort(np.linalg.norm(env.crowd.pos - env.robot[:2], axis=1))[:5]
    np.testing.assert_allclose(d, true_d, atol=1e-5)
    # back to the world frame
    k = int(np.argmin(np.linalg.norm(env.crowd.pos - env.robot[:2], axis=1)))
    wx = x + c * peds[0, 0] - s * peds[0, 1]
    wy = y + s * peds[0, 0] + c * peds[0, 1]
    np.testing.assert_allclose([wx, wy], env.crowd.pos[k], atol=1e-5)
    np.testing.assert_allclose(peds[0, 4], env.crowd.radius[k], atol=1e-6)
    ang = yaw + np.arange(72) * 2 * np.pi / 72
    np.testing.assert_allclose(obs["scan"], env.layout.geometry.raycast(env.robot[:2], ang, 10.0), atol=1e-5)
    np.testing.assert_allclose(obs["scan"], info["privileged"]["static_scan"], atol=1e-5)


def test_privileged_peds_are_zero_padded():
    env = CrowdNavEnv(scene="hallway", density=0.05, obs_mode="privileged", privileged_peds=10)
    obs, _ = env.reset(seed=0)
    n = env.crowd.n
    assert 0 < n < 10
    assert (obs["peds"][:n, 5] == 1).all() and (obs["peds"][n:] == 0).all()


def test_pedestrians_spawn_away_from_start_and_goal():
    env = state_env(density=0.3)
    for seed in range(3):
        env.reset(seed=seed)
        for p in (env.start, env.goal):
            assert np.all(np.linalg.norm(env.crowd.pos - p, axis=1) >= 1.0 + 0.3)


# --------------------------------------------------------------------------------------------- termination
def test_collision_with_a_wall_terminates():
    env = state_env(scene="hallway", density=0.0)
    env.reset(seed=2)
    env.robot[2] = math.pi / 2  # face the north wall
    prev_static = env.d_static
    for _ in range(40):
        obs, reward, terminated, truncated, info = env.step(env.encode_command(1.0, 0.0))
        if terminated or truncated:
            break
        assert info["outcome"] is None and reward == pytest.approx(info["reward_terms"]["total"])
        prev_static = env.d_static
    assert terminated and not truncated
    assert info["outcome"] == "collision_obstacle"
    assert reward == -20.0 and info["reward_terms"]["collision"] == -20.0
    assert info["d_o"] <= 0.3 < prev_static  # ends on the first step that touches


def test_collision_with_a_pedestrian_terminates():
    fa = load_scene("open_crowd").layout().free_area_m2
    cfg = SimConfig(crowd=CrowdConfig(react_to_robot=False))
    env = CrowdNavEnv(scene="open_crowd", density=1.0 / fa, obs_mode="state", config=cfg)
    env.reset(seed=0)
    assert env.crowd.n == 1
    x, y, yaw = env.robot
    env.crowd.pos[0] = [x + 0.75 * math.cos(yaw), y + 0.75 * math.sin(yaw)]
    env.crowd.vel[0] = 0.0
    env.crowd.goal[0] = env.crowd.pos[0]
    env.crowd.mode[0] = 1  # standing
    env.crowd.idle_left[0] = 10.0
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(env.encode_command(1.0, 0.0))
        if terminated:
            break
    assert terminated
    assert info["outcome"] == "collision_pedestrian"
    assert info["reward_terms"]["collision"] == -20.0 and reward == -20.0
    assert env.trace().outcome == "collision_pedestrian"


def test_expert_reaches_the_goal_and_the_episode_ends_in_success():
    env = state_env(scene="hallway", density=0.0)
    expert = PrivilegedExpert()
    env.reset(seed=0)
    expert.reset(env)
    total, steps = 0.0, 0
    while True:
        obs, reward, terminated, truncated, info = env.step(env.encode_command(*expert.command(env)))
        total += reward
        steps += 1
        if terminated or truncated:
            break
    assert terminated and not truncated and info["outcome"] == "success"
    assert info["reward_terms"]["success"] == 20.0 and info["d_goal"] <= env.cfg.goal_radius_m
    assert info["time_s"] == pytest.approx(steps * 0.1) and info["time_s"] < env.cfg.max_episode_s
    # +20 at the end, plus progress (minus small penalties within 0.9 m of walls) before
    assert total > 20.0


def test_goal_radius_not_robot_radius_decides_success():
    env = state_env(scene="hallway", density=0.0, config=SimConfig(goal_radius_m=0.6))
    assert env.cfg.robot.radius_m == 0.3  # != the goal radius, so a swap of the two in the reward call shows
    env.reset(seed=0)
    toward_start = (env.start - env.goal) / np.linalg.norm(env.start - env.goal)
    x, y = env.goal + 0.45 * toward_start  # within the goal radius, outside the robot's own radius
    env.robot = np.array([x, y, math.atan2(-toward_start[1], -toward_start[0])])
    obs, reward, terminated, truncated, info = env.step(env.encode_command(0.0, 0.0))
    assert info["d_goal"] == pytest.approx(0.45, abs=1e-6)
    assert terminated and info["outcome"] == "success" and info["reward_terms"]["success"] == 20.0


def test_truncated_at_max_episode_s():
    env = state_env(density=0.0, max_episode_s=1.0)
    env.reset(seed=0)
    stay = env.encode_command(0.0, 0.0)
    for k in range(1, 11):
        obs, reward, terminated, truncated, info = env.step(stay)
        assert not terminated
        assert truncated == (k == 10), k
    assert info["outcome"] == "timeout" and info["time_s"] == pytest.approx(1.0)
    assert reward == 0.0  # standing still far from everything: no progress, no penalty


def test_step_before_reset_raises():
    env = state_env()
    with pytest.raises(RuntimeError, match="reset"):
        env.step(env.action_space.sample())


# ---------------------------------------------------------------------------------------------------- info
def test_info_contents():
    env = CrowdNavEnv(scene="office_lobby", density=0.15, obs_mode="state", info_level="full")
    obs, info = env.reset(seed=7)
    n = env.crowd.n
    assert env.shortest_path_m >= np.hypot(*(env.goal - env.start)) - 0.2  # computed on first use
    assert isinstance(info["episode_seed"], int)
    occ = info["occupancy"]
    assert occ["grid"].dtype == bool and occ["resolution_m"] == 0.05
    rng = np.random.default_rng(0)
    for _ in range(10):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        terms = info["reward_terms"]
        assert set(terms) == {"success", "collision", "near", "progress", "spin", "total"}
        assert reward == pytest.approx(sum(v for k, v in terms.items() if k != "total"))
        assert reward == pytest.approx(terms["total"])
        if terminated or truncated:
            break
    p = info["privileged"]
    assert p["keypoints_world"].shape == (n, 17, 3)
    assert p["ped_pos"].shape == (n, 2) and p["ped_head_yaw"].shape == (n,) and p["ped_intent_xy"].shape == (n, 2)
    assert p["static_scan"].shape == (72,)
    assert (p["ped_lead_s"] >= 0).all()
    np.testing.assert_allclose(p["robot_pose"], env.robot)
    d_ped = np.min(np.linalg.norm(p["ped_pos"] - env.robot[:2], axis=1) - p["ped_radius"])
    d_static = env.layout.clearance_at(env.robot[:2])
    assert info["d_o"] == pytest.approx(min(d_ped, d_static))
    assert info["d_goal"] == pytest.approx(np.hypot(*(env.goal - env.robot[:2])))
    # keypoints stand on the pedestrians' positions
    np.testing.assert_allclose(p["keypoints_world"][..., :2].mean(1), p["ped_pos"], atol=0.35)
    basic = state_env(density=0.15)
    _, info_b = basic.reset(seed=7)
    assert "keypoints_world" not in info_b["privileged"] and "static_scan" not in info_b["privileged"]


def test_trace_has_consistent_shapes():
    env = state_env(density=0.1)
    env.reset(seed=3)
    actions = [np.array([0.5, 0.2], np.float32)] * 15
    poses = [env.robot.copy()]
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        poses.append(env.robot.copy())
        if terminated or truncated:
            break
    tr = env.trace(method="test")
    t, n = len(poses) - 1, env.crowd.n
    assert tr.n_steps == t and tr.n_peds == n
    assert tr.robot_pose.shape == (t + 1, 3) and tr.robot_cmd.shape == (t, 2)
    assert tr.ped_xy.shape == (t + 1, n, 2) and tr.ped_vel.shape == (t + 1, n, 2)
    assert tr.ped_yaw.shape == (t + 1, n) and tr.ped_head_yaw.shape == (t + 1, n)
    assert tr.static_clearance_m.shape == (t + 1,) and tr.ped_radius.shape == (n,)
    np.testing.assert_allclose(tr.robot_pose, np.array(poses))
    np.testing.assert_allclose(tr.robot_cmd[0], env.decode_action(actions[0]))
    np.testing.assert_allclose(tr.ped_xy[-1], env.crowd.pos)
    assert tr.method == "test" and tr.scene == "office_lobby" and tr.seed == 3 and tr.density == 0.1
    assert tr.outcome == "timeout"
    tr.validate()


def test_trace_without_pedestrians():
    env = state_env(scene="hallway", density=0.0)
    env.reset(seed=0)
    for _ in range(3):
        env.step(env.encode_command(0.5, 0.0))
    tr = env.trace()
    assert tr.ped_xy.shape == (4, 0, 2) and tr.ped_yaw.shape == (4, 0)


def test_top_down_render():
    env = CrowdNavEnv(scene="office_lobby", density=0.1, obs_mode="state", render_mode="rgb_array")
    assert env.render() is None  # before reset
    env.reset(seed=0)
    env.step(env.action_space.sample())
    img = env.render()
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.shape[1] > img.shape[0]  # a 14 x 7 m scene
    assert CrowdNavEnv(obs_mode="state").render() is None  # no render mode


# -------------------------------------------------------------------------------------------------- errors
@pytest.mark.parametrize("kwargs,words", [
    (dict(scene="nowhere"), ["'nowhere'", "office_lobby"]),
    (dict(density=-0.1), ["density", "-0.1"]),
    (dict(density=float("nan")), ["density"]),
    (dict(density=5.0), ["density", "5.0"]),
    (dict(config=SimConfig(camera=CameraConfig(width_px=0))), ["camera resolution", "0x120"]),
    (dict(config=SimConfig(camera=CameraConfig(height_px=10_000))), ["camera resolution", "160x10000"]),
    (dict(colour="red"), ["unknown option 'colour'"]),
    (dict(obs_mode="pixels"), ["obs_mode", "'pixels'"]),
    (dict(action_type="joystick"), ["action_type", "'joystick'"]),
    (dict(info_level="all"), ["info_level"]),
    (dict(render_mode="human"), ["render_mode", "'human'"]),
    (dict(dt_s=0.0), ["dt_s"]),
    (dict(config=SimConfig(robot=RobotConfig(radius_m=-1.0))), ["robot.radius_m"]),
])
def test_bad_input_raises_config_error(kwargs, words):
    with pytest.raises(ConfigError) as ei:
        CrowdNavEnv(**kwargs)
    msg = str(ei.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, (w, msg)


def test_bad_input_through_gymnasium_make():
    with pytest.raises(ConfigError, match="unknown scene 'nowhere'"):
        gymnasium.make("icrowdnav/CrowdNav-v0", scene="nowhere")


def test_same_seed_same_episode_whatever_ran_before_in_the_process():
    """Caches (free cells, graphs, layouts) must not make an episode depend on the process's history."""

    def run(seed):
        env = state_env("warehouse", 0.2, info_level="basic")
        env.reset(seed=seed)
        for _ in range(30):
            env.step(np.array([0.5, 0.1], np.float32))
        return env.trace()

    first = run(11)
    for s in range(3):  # other episodes with other crowds (other pedestrian radii hit the caches)
        run(100 + s)
        state_env("office_lobby", 0.3).reset(seed=s)
    again = run(11)
    np.testing.assert_array_equal(first.ped_xy, again.ped_xy)
    np.testing.assert_array_equal(first.robot_pose, again.robot_pose)


def test_privileged_subgoal_follows_the_global_path():
    env = CrowdNavEnv(scene="corner", density=0.0, obs_mode="privileged")
    obs, _ = env.reset(seed=1)
    sub = obs["subgoal"]
    assert sub.shape == (2,) and np.hypot(*sub) <= env.cfg.subgoal_lookahead_m + 1e-5
    x, y, yaw = env.robot
    c, s = math.cos(yaw), math.sin(yaw)
    world = np.array([x + c * sub[0] - s * sub[1], y + s * sub[0] + c * sub[1]])
    # on a collision-free straight segment from the robot (the path is string-pulled)
    assert env.layout.segments_min_clearance(env.robot[None, :2], world[None])[0] > env.cfg.robot.radius_m
    # the shortest path is shorter through the sub-goal than from anywhere else 2 m away in the open direction
    d_via = np.hypot(*(world - env.robot[:2])) + env.layout.path_length(world, env.goal, env.cfg.robot.radius_m)
    assert d_via <= env.shortest_path_m + 0.1
    # in line of sight and nearer than the lookahead, the sub-goal is the target itself
    near = env.robot[:2] + np.array([c, s]) * 0.6
    if env.layout.segments_min_clearance(env.robot[None, :2], near[None])[0] > 0.4:
        np.testing.assert_allclose(env.privileged_subgoal(near), [0.6, 0.0], atol=1e-4)


def test_privileged_subgoal_in_an_open_room_points_at_the_goal():
    env = CrowdNavEnv(scene="open_crowd", density=0.0, obs_mode="privileged")
    for seed in range(6):
        obs, _ = env.reset(seed=seed)
        if env.layout.segments_min_clearance(env.robot[None, :2], env.goal[None])[0] > 0.5:
            break
    g = obs["state"][:2]
    expected = g / np.hypot(*g) * min(env.cfg.subgoal_lookahead_m, float(np.hypot(*g)))
    np.testing.assert_allclose(obs["subgoal"], expected, atol=0.05)


def test_privileged_path_points_follow_the_route():
    env = CrowdNavEnv(scene="corner", density=0.0, obs_mode="privileged")
    obs, _ = env.reset(seed=1)
    path = obs["path"]
    assert path.shape == (env.cfg.path_points, 2) and env.observation_space["path"].contains(path)
    steps = np.hypot(*np.diff(np.vstack([[0.0, 0.0], path]), axis=0).T)
    # consecutive points are one spacing apart along the path (chords are never longer), nearer to the goal
    assert np.all(steps[1:] <= env.cfg.path_spacing_m + 1e-5) and np.all(steps[1:] > 0.5 * env.cfg.path_spacing_m)
    k = int(round(env.cfg.subgoal_lookahead_m / env.cfg.path_spacing_m)) - 1
    np.testing.assert_allclose(path[k], obs["subgoal"], atol=1e-4)  # the sub-goal is the point 2 m along


def test_time_limit_follows_the_shortest_path():
    """The benchmark's rule: limit = max(max_episode_s, timeout_s_per_m x shortest start-goal path)."""
    env = state_env("office_lobby", 0.0, max_episode_s=5.0, timeout_s_per_m=2.0)
    env.reset(seed=3)
    length = env.shortest_path_m
    assert env.time_limit_s == pytest.approx(max(5.0, 2.0 * length))
    assert 2.0 * length > 5.0  # a ~6 m path: the route, not the floor, sets the limit here
    steps = 0
    truncated = terminated = False
    while not (terminated or truncated):
        _, _, terminated, truncated, info = env.step(env.encode_command(0.0, 0.0))  # stand still
        steps += 1
    assert truncated and info["outcome"] == "timeout"
    assert steps == math.ceil(env.time_limit_s / env.cfg.dt_s - 1e-6)
    off = state_env("office_lobby", 0.0, max_episode_s=5.0)  # timeout_s_per_m = 0: the floor alone
    off.reset(seed=3)
    assert off.time_limit_s == 5.0


def test_time_limit_rule_rejects_bad_values():
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="timeout_s_per_m"):
            state_env(timeout_s_per_m=bad)


def test_scene_seed_fixes_start_goal_and_clutter_and_the_seed_the_crowd():
    """The benchmark's goals x trials: every trial of a goal starts alike; only the people differ."""
    env = state_env("warehouse", 0.1)
    runs = []
    for seed in (11, 12):
        env.reset(seed=seed, options={"scene_seed": 500})
        runs.append((env.start.copy(), env.goal.copy(), env.robot.copy(),
                     [o.center for o in env.layout.obstacles], env.crowd.pos.copy()))
    (s0, g0, r0, o0, c0), (s1, g1, r1, o1, c1) = runs
    np.testing.assert_array_equal(s0, s1)
    np.testing.assert_array_equal(g0, g1)
    np.testing.assert_array_equal(r0, r1)
    assert o0 == o1
    assert not np.array_equal(c0, c1)
    env.reset(seed=11, options={"scene_seed": 501})
    assert not np.array_equal(env.start, s0)
    env.reset(seed=11)  # without the option the seed draws everything, as before
    assert not np.array_equal(env.start, s0)


@pytest.mark.parametrize("key,value", [("max_episode_s", float("inf")), ("max_episode_s", float("nan")),
                                       ("dt_s", float("nan")), ("dt_s", float("inf"))])
def test_non_finite_timing_is_a_named_error(key, value):
    """NaN passes every comparison and inf switches the timeout off: both are refused by name."""
    with pytest.raises(ConfigError, match=f"{key}: expected a finite number"):
        state_env(**{key: value})
