"""Tests of sim.crowd: the vectorised social force against the reference loop, walls, speeds, the robot force."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim.crowd import IDLE, WALK, Crowd, CrowdConfig, heading_of, social_force_reference
from sim.humans import Bodies, BodyConfig
from sim.scene import load_scene


def make_crowd(scene: str, density: float, seed: int, cfg: CrowdConfig | None = None, layout=None):
    rng = np.random.default_rng(seed)
    layout = layout or load_scene(scene).layout(np.random.default_rng(seed))
    n = layout.ped_count(density)
    bodies = Bodies(BodyConfig(), rng, n, np.zeros(n))
    return Crowd(layout, cfg or CrowdConfig(), rng, n, bodies.radius)


def scramble(crowd: Crowd, rng: np.random.Generator) -> None:
    """Random velocities, goals and modes, so every force term is exercised."""
    n = crowd.n
    crowd.vel = rng.normal(0.0, 0.8, (n, 2))
    crowd.vel[0] = 0.0  # a standing pedestrian (zero-speed direction)
    crowd.goal = crowd.layout.free_points(rng, n, 0.4)
    crowd.goal[1] = crowd.pos[1] + [0.2, 0.1]  # close to its goal: slowing down
    crowd.mode = np.where(rng.random(n) < 0.3, IDLE, WALK).astype(np.int8)


def reference(crowd: Crowd, robot_xy=None, robot_radius=0.3):
    return social_force_reference(crowd.pos, crowd.vel, crowd.goal, crowd.v0, crowd.radius, crowd.mode, crowd.layout,
                                  crowd.cfg, robot_xy, robot_radius)


@pytest.mark.parametrize("scene,density,seed", [("office_lobby", 0.2, 0), ("warehouse", 0.15, 1),
                                                ("open_crowd", 0.3, 2)])
def test_vectorised_social_forces_equal_reference(scene, density, seed):
    crowd = make_crowd(scene, density, seed)
    rng = np.random.default_rng(seed + 10)
    scramble(crowd, rng)
    # a pair far apart (> interaction range) and a pair squeezed together
    crowd.pos[2] = crowd.pos[3] + [0.45, 0.0]
    np.testing.assert_allclose(crowd.social_forces(None, 0.3), reference(crowd), rtol=1e-9, atol=1e-9)
    robot = crowd.pos[4] + np.array([0.6, -0.2])
    f_robot = crowd.social_forces(robot, 0.3)
    np.testing.assert_allclose(f_robot, reference(crowd, robot, 0.3), rtol=1e-9, atol=1e-9)
    assert np.linalg.norm(f_robot[4] - crowd.social_forces(None, 0.3)[4]) > 0.5  # the robot force is there


def test_social_forces_equal_reference_over_a_simulation():
    crowd = make_crowd("office_lobby", 0.2, 3)
    robot = np.array([7.0, 3.5])
    for k in range(60):
        crowd.step(0.1, robot, 0.3)
        if k % 20 == 19:
            np.testing.assert_allclose(crowd.social_forces(robot, 0.3), reference(crowd, robot, 0.3),
                                       rtol=1e-9, atol=1e-9)


def test_single_pedestrian_and_empty_crowd():
    layout = load_scene("open_crowd").layout()
    for n in (0, 1):
        rng = np.random.default_rng(0)
        crowd = Crowd(layout, CrowdConfig(), rng, n, np.full(n, 0.25))
        f = crowd.social_forces(np.array([6.0, 6.0]), 0.3)
        assert f.shape == (n, 2)
        np.testing.assert_allclose(f, reference(crowd, np.array([6.0, 6.0])), atol=1e-12)
        crowd.step(0.1, np.array([6.0, 6.0]))
        assert crowd.pos.shape == (n, 2)


def test_pairwise_force_is_repulsive_and_decays_with_distance():
    layout = load_scene("open_crowd").layout()
    crowd = Crowd(layout, CrowdConfig(), np.random.default_rng(0), 2, np.full(2, 0.25))
    crowd.vel[:] = 0.0
    crowd.mode[:] = IDLE
    crowd.goal = crowd.pos.copy()
    mags = []
    for gap in (0.6, 1.0, 2.0):
        crowd.pos = np.array([[6.0, 6.0], [6.0 + gap, 6.0]])
        crowd.goal = crowd.pos.copy()
        f = crowd.social_forces(None, 0.3)
        assert f[0, 0] < 0 < f[1, 0]  # pushed apart along the line joining them
        np.testing.assert_allclose(f[0], -f[1], atol=1e-5)  # symmetric when both stand still (walls far)
        mags.append(abs(f[0, 0]))
    assert mags[0] > mags[1] > mags[2]


@pytest.mark.parametrize("scene,seed", [("office_lobby", 0), ("office_lobby", 1), ("warehouse", 0),
                                        ("warehouse", 2)])
def test_pedestrians_stay_out_of_walls_and_under_the_speed_cap(scene, seed):
    crowd = make_crowd(scene, 0.2, seed)
    assert crowd.n >= 15
    layout = crowd.layout
    robot = np.array(layout.free_points(np.random.default_rng(seed), 1, 0.5)[0])
    worst, fastest = np.inf, 0.0
    for _ in range(300):
        crowd.step(0.1, robot, 0.3)
        worst = min(worst, float(np.min(layout.clearance_at(crowd.pos) - crowd.radius)))
        fastest = max(fastest, float(np.max(np.linalg.norm(crowd.vel, axis=1) / crowd.v0)))
        assert np.all(np.isfinite(crowd.pos))
    assert worst >= -0.02
    assert fastest <= 1.3 + 1e-9
    x0, x1, y0, y1 = layout.spec.bounds
    assert np.all((crowd.pos[:, 0] > x0) & (crowd.pos[:, 0] < x1) & (crowd.pos[:, 1] > y0) & (crowd.pos[:, 1] < y1))


def test_pedestrians_actually_move_and_reach_goals():
    crowd = make_crowd("office_lobby", 0.1, 5)
    start = crowd.pos.copy()
    walked = np.zeros(crowd.n)
    goals_seen = [crowd.goal.copy()]
    for _ in range(300):
        prev = crowd.pos.copy()
        crowd.step(0.1)
        walked += np.linalg.norm(crowd.pos - prev, axis=1)
        goals_seen.append(crowd.goal.copy())
    assert np.median(walked) > 10.0  # ~30 s at ~1 m/s, minus idling
    assert np.median(np.linalg.norm(crowd.pos - start, axis=1)) > 1.0
    changed = (np.abs(np.diff(np.array(goals_seen), axis=0)).sum(-1) > 0).sum(0)
    assert np.all(changed >= 1)  # everybody picked at least one new goal


def test_spawn_keeps_distance_from_avoid_points_and_each_other():
    layout = load_scene("office_lobby").layout()
    avoid = [np.array([3.0, 3.0]), np.array([10.0, 4.0])]
    crowd = Crowd(layout, CrowdConfig(), np.random.default_rng(0), 15, np.full(15, 0.25), avoid_xy=avoid,
                  avoid_m=1.3)
    for a in avoid:
        assert np.all(np.linalg.norm(crowd.pos - a, axis=1) >= 1.3)
    d = np.linalg.norm(crowd.pos[:, None] - crowd.pos[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    assert d.min() >= 0.8
    assert np.all(layout.clearance_at(crowd.pos) >= 0.25)


def test_react_to_robot_false_removes_the_robot_force():
    for react in (True, False):
        crowd = make_crowd("open_crowd", 0.1, 4, CrowdConfig(react_to_robot=react))
        scramble(crowd, np.random.default_rng(1))
        robot = crowd.pos[2] + np.array([0.5, 0.0])
        with_robot = crowd.social_forces(robot, 0.3)
        without = crowd.social_forces(None, 0.3)
        if react:
            assert np.abs(with_robot - without).max() > 0.5
            assert with_robot[2, 0] < without[2, 0]  # pushed away from the robot (in -x)
        else:
            np.testing.assert_array_equal(with_robot, without)


def test_robot_makes_pedestrians_give_way():
    """A pedestrian walking at a standing robot deviates from its straight line only when it reacts."""
    layout = load_scene("open_crowd").layout()
    lateral = {}
    for react in (True, False):
        cfg = CrowdConfig(react_to_robot=react, turn_rate_hz=0.0, idle_prob=0.0)
        crowd = Crowd(layout, cfg, np.random.default_rng(0), 1, np.full(1, 0.25))
        crowd.pos[:] = [[2.0, 6.0]]
        crowd.vel[:] = [[1.0, 0.0]]
        crowd.goal[:] = [[10.5, 6.0]]
        crowd.pending[:] = crowd.goal
        min_gap = np.inf
        robot = np.array([6.0, 6.02])
        for _ in range(50):
            crowd.step(0.1, robot, 0.3)
            min_gap = min(min_gap, float(np.linalg.norm(crowd.pos[0] - robot)))
        lateral[react] = min_gap
    assert lateral[True] > 0.3 + 0.25  # kept clear of the robot's footprint
    assert lateral[False] < 0.2  # walked (almost) through it


def test_idle_pedestrians_stop_and_lead_times_are_in_range():
    cfg = CrowdConfig(idle_prob=1.0)
    crowd = make_crowd("office_lobby", 0.1, 6, cfg)
    leads, idled = [], False
    for _ in range(200):
        before = crowd.lead.copy()
        crowd.step(0.1)
        new = (crowd.lead > 0) & (before <= 0)
        leads.extend(crowd.lead[new].tolist())  # freshly drawn this step (the countdown ran before the draw)
        idled |= bool((crowd.mode == IDLE).any())
    assert idled
    assert leads
    assert min(leads) >= cfg.lead_min_s and max(leads) <= cfg.lead_max_s
    # idle pedestrians have no desired velocity
    crowd.mode[:] = IDLE
    np.testing.assert_array_equal(crowd.desired_velocity(), 0.0)


def test_attention_is_the_pending_goal_during_a_lead():
    crowd = make_crowd("open_crowd", 0.05, 0)
    crowd.lead[:] = 0.0
    np.testing.assert_array_equal(crowd.attention_xy(), crowd.goal)
    crowd.pending = crowd.goal + 1.0
    crowd.lead[0] = 0.5
    att = crowd.attention_xy()
    np.testing.assert_array_equal(att[0], crowd.pending[0])
    np.testing.assert_array_equal(att[1:], crowd.goal[1:])
    sd = crowd.state_dict()
    assert set(sd) == {"pos", "vel", "radius", "goal", "pending", "lead_s", "mode"}
    sd["pos"][:] = -99
    assert not np.any(crowd.pos == -99)  # copies


def test_crowd_is_deterministic_for_a_seed():
    a = make_crowd("office_lobby", 0.15, 9)
    b = make_crowd("office_lobby", 0.15, 9)
    for _ in range(100):
        a.step(0.1, np.array([7.0, 3.5]))
        b.step(0.1, np.array([7.0, 3.5]))
    np.testing.assert_array_equal(a.pos, b.pos)
    np.testing.assert_array_equal(a.vel, b.vel)


def test_heading_of():
    v = np.array([[1.0, 0.0], [0.0, 2.0], [0.0, 0.0]])
    np.testing.assert_allclose(heading_of(v, np.array([0.3, 0.3, 0.3])), [0.0, np.pi / 2, 0.3])


def test_farthest_goal_choice_spreads_the_crowd_along_the_corridors():
    """In the L-junction, random goals in range crowd the arms' middles; farthest visible goals fill the ends."""
    base = load_scene("corner")
    ends = {}
    for choice in ("first", "farthest"):
        layout = dataclasses.replace(base, ped_goal_choice=choice).layout()
        at_end, total = 0, 0
        for seed in range(4):
            crowd = Crowd(layout, CrowdConfig(), np.random.default_rng(seed), 10, np.full(10, 0.25))
            for k in range(600):
                crowd.step(0.1, None)
                if k >= 100:
                    p = crowd.pos
                    at_end += int(np.sum((p[:, 0] < 2.0) | (p[:, 1] > 8.0)))  # the far 2 m of each arm
                    total += len(p)
        ends[choice] = at_end / total
    assert ends["farthest"] > 1.3 * ends["first"], ends
