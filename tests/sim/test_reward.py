"""Tests of sim.reward: the paper's reward (Eq. 9-10), term by term on constructed values."""

from __future__ import annotations

import itertools

import pytest

from sim.reward import RewardConfig, reward_terms

CFG = RewardConfig()
RHO = 0.3  # robot radius
GOAL_R = 0.3
NAV = ("success", "collision", "near", "progress")


def terms(d_goal, d_goal_prev, d_o, omega=0.0, cfg=CFG):
    return reward_terms(cfg, d_goal, d_goal_prev, d_o, omega, RHO, GOAL_R)


def test_paper_defaults():
    assert (CFG.success, CFG.collision, CFG.near_weight, CFG.near_distance_m) == (20.0, -20.0, 0.5, 0.9)
    assert (CFG.progress_weight, CFG.spin_weight, CFG.spin_threshold_radps) == (3.2, 0.1, 1.0)


@pytest.mark.parametrize("d_goal", [0.0, 0.1, 0.3])
def test_success_when_within_goal_radius(d_goal):
    t = terms(d_goal, 0.5, d_o=2.0)
    assert t["success"] == 20.0
    assert t["collision"] == t["near"] == t["progress"] == 0.0


def test_success_takes_precedence_over_collision():
    t = terms(0.2, 0.4, d_o=0.1)
    assert t["success"] == 20.0 and t["collision"] == 0.0


@pytest.mark.parametrize("d_o", [-0.2, 0.0, 0.15, 0.3])
def test_collision_when_footprints_touch(d_o):
    t = terms(3.0, 3.1, d_o)
    assert t["collision"] == -20.0
    assert t["success"] == t["near"] == t["progress"] == 0.0


@pytest.mark.parametrize("d_o", [0.31, 0.5, 0.7, 0.899])
def test_near_penalty_between_radius_and_0_9(d_o):
    t = terms(3.0, 3.1, d_o)
    assert t["near"] == pytest.approx(0.5 * (d_o - 0.9))
    assert t["near"] < 0
    assert t["success"] == t["collision"] == t["progress"] == 0.0


@pytest.mark.parametrize("prev,now", [(3.1, 3.0), (3.0, 3.1), (5.0, 4.25)])
def test_progress_otherwise(prev, now):
    t = terms(now, prev, d_o=0.9)  # the near penalty stops at exactly 0.9 m
    assert t["progress"] == pytest.approx(3.2 * (prev - now))
    assert t["success"] == t["collision"] == t["near"] == 0.0
    t = terms(now, prev, d_o=float("inf"))  # an empty scene
    assert t["progress"] == pytest.approx(3.2 * (prev - now))


@pytest.mark.parametrize("omega,spin", [(0.0, 0.0), (0.9, 0.0), (1.0, 0.0), (-1.0, 0.0), (1.01, -0.101),
                                        (-1.5, -0.15), (2.0, -0.2)])
def test_spin_penalty_only_above_1_rad_per_s(omega, spin):
    assert terms(3.0, 3.1, 2.0, omega)["spin"] == pytest.approx(spin)


def test_exactly_one_nav_term_and_total_is_the_sum():
    d_goals = [0.1, 0.3, 0.31, 2.0]
    d_os = [0.0, 0.3, 0.5, 0.9, 3.0]
    omegas = [0.0, 1.5, -2.0]
    for d_goal, d_o, omega in itertools.product(d_goals, d_os, omegas):
        t = terms(d_goal, d_goal + 0.07, d_o, omega)
        assert set(t) == {*NAV, "spin", "total"}
        assert sum(t[k] != 0.0 for k in NAV) == 1, (d_goal, d_o, omega, t)
        assert t["total"] == pytest.approx(sum(t[k] for k in (*NAV, "spin")))


def test_config_weights_are_used():
    cfg = RewardConfig(success=5.0, collision=-7.0, near_weight=2.0, near_distance_m=1.5, progress_weight=1.0,
                       spin_weight=1.0, spin_threshold_radps=0.5)
    assert terms(0.1, 0.2, 3.0, cfg=cfg)["success"] == 5.0
    assert terms(2.0, 2.1, 0.2, cfg=cfg)["collision"] == -7.0
    assert terms(2.0, 2.1, 1.0, cfg=cfg)["near"] == pytest.approx(2.0 * (1.0 - 1.5))
    assert terms(2.0, 2.5, 1.6, cfg=cfg)["progress"] == pytest.approx(0.5)
    assert terms(2.0, 2.5, 1.6, 0.75, cfg=cfg)["spin"] == pytest.approx(-0.75)


@pytest.mark.parametrize("robot_r,goal_r", [(0.3, 0.6), (0.6, 0.3)])
def test_goal_radius_and_robot_radius_are_not_interchangeable(robot_r, goal_r):
    """Every other test uses robot radius = goal radius; here they differ, and each must gate its own case."""
    # 0.45 m from the goal: success only when the goal radius (not the robot's) reaches that far
    t = reward_terms(CFG, 0.45, 0.6, 2.0, 0.0, robot_r, goal_r)
    assert t["success"] == (20.0 if goal_r > 0.45 else 0.0), t
    if goal_r < 0.45:
        assert t["progress"] == pytest.approx(3.2 * 0.15) and t["total"] == pytest.approx(0.48)
    # a surface 0.45 m from the robot centre: a collision only when the robot radius reaches that far
    t = reward_terms(CFG, 3.0, 3.1, 0.45, 0.0, robot_r, goal_r)
    if robot_r > 0.45:
        assert t["collision"] == -20.0 and t["near"] == 0.0 and t["total"] == -20.0, t
    else:
        assert t["collision"] == 0.0 and t["near"] == pytest.approx(0.5 * (0.45 - 0.9)), t
