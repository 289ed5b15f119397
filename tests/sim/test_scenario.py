"""Scenario files: parsing and named errors, trigger timing, the scripted pedestrian's head lead before a turn,
determinism, and the metrics (collision with / clearance to the scripted pedestrian, reaction time)."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import yaml

from pipeline.core.errors import ConfigError, InputMissingError
from sim.env import CrowdNavEnv
from sim.geometry import wrap_angle
from sim.scenario import (
    SCENARIOS_DIR,
    available_scenarios,
    cue_twin_metrics,
    load_scenario,
    parse_scenario,
    reaction_time_s,
    scenario_metrics,
)

SHIPPED = ["blind_corner", "crossing_turn", "doorway", "head_on", "overtaking"]


def _data(name: str) -> dict:
    return yaml.safe_load((SCENARIOS_DIR / f"{name}.yaml").read_text())


def _env(scenario: str, **kw) -> CrowdNavEnv:
    kw.setdefault("obs_mode", "state")
    kw.setdefault("info_level", "basic")
    return CrowdNavEnv(scenario=scenario, density=0.0, **kw)


def _reset_facing_east(env: CrowdNavEnv, seed: int) -> None:
    env.reset(seed=seed)
    env.robot[2] = 0.0  # the trial's heading jitter undone: these tests drive straight along the corridor


def test_shipped_scenarios_load():
    assert available_scenarios() == SHIPPED
    for name in SHIPPED:
        sc = load_scenario(name)
        assert sc.name == name and sc.pedestrians
        assert sc.scene.random_obstacles is None


def test_blind_corner_layout_is_two_corridors_with_solid_inner_corners():
    layout = load_scenario("blind_corner").scene.layout()
    assert np.all(layout.clearance_at(np.array([[1.5, 1.5], [12.5, 1.5], [7.5, 8.0]])) > 0.5)
    inner = np.array([[5.5, 3.5], [9.5, 3.5]])  # just beside the junction: solid, so the walker is hidden
    assert np.all(layout.geometry.signed_distance(inner)[0] < 0)


def _bad(name: str, edit) -> str:
    data = copy.deepcopy(_data(name))
    edit(data)
    with pytest.raises(ConfigError) as e:
        parse_scenario(data, f"{name}.yaml", name)
    return str(e.value)


@pytest.mark.parametrize("edit,match", [
    (lambda d: d.update(layout=None, scene="no_such_scene"), r"'scene'.*unknown scene 'no_such_scene'"),
    (lambda d: d["pedestrians"][0]["waypoints"].__setitem__(0, [3.0, 6.0]), r"waypoints\[0\].*outside every obstacle"),
    (lambda d: d.update(goal=[7.5, 8.0], start=[3.0, 7.0]), r"'start'.*free start"),
    (lambda d: d["pedestrians"][0]["trigger"].update(point=[7.5, 9.0], robot_within_m=1.0), r"could never fire"),
    (lambda d: d["pedestrians"][0].update(speed_mps=float("nan")), r"speed_mps.*finite"),
    (lambda d: d.update(start=[float("inf"), 1.5]), r"'start\[0\]'.*finite"),
    (lambda d: d["pedestrians"][0]["trigger"].update(time_s=2.0), r"exactly one of time_s / robot_within_m"),
    (lambda d: d.update(scene="corner"), r"exactly one of 'scene'.*both"),
    (lambda d: d.update(pedestrians=[]), r"pedestrians.*1 to 20"),
    (lambda d: d.update(speed_jitter=0.9), r"speed_jitter.*\[0, 0.5\]"),
])
def test_bad_scenarios_are_one_named_error(edit, match):
    msg = _bad("blind_corner", edit)
    assert msg.startswith("scenario file blind_corner.yaml")
    assert __import__("re").search(match, msg), msg


def test_unreachable_goal_is_a_named_error():
    def edit(d):
        d["layout"]["free_space"] = [[0.0, 6.0, 0.0, 3.0], [8.0, 14.0, 0.0, 3.0], [6.0, 9.0, 3.0, 10.0]]
        d["layout"]["obstacles"] = [{"box": {"center": [7.0, 1.5], "size": [2.0, 3.0]}}]
    assert "no path from" in _bad("blind_corner", edit)


def test_walk_through_a_wall_is_a_named_error():
    def edit(d):
        d["pedestrians"][0]["waypoints"] = [[7.5, 1.8], [3.0, 1.8], [3.0, 6.0]]
    msg = _bad("blind_corner", edit)
    assert "waypoints[2]" in msg


def test_unknown_scenario_and_missing_file():
    with pytest.raises(ConfigError, match="unknown scenario 'nope'; known scenarios: blind_corner"):
        load_scenario("nope")
    with pytest.raises(InputMissingError):
        load_scenario("/no/such/scenario.yaml")


def test_distance_trigger_fires_when_the_robot_comes_within_the_distance():
    env = _env("blind_corner")
    _reset_facing_east(env, 0)
    ped = load_scenario("blind_corner").pedestrians[0]
    i = env.crowd.n_random
    start = env.crowd.pos[i].copy()
    fired_at = None
    for _k in range(200):
        before = env.robot[:2].copy()
        env.step(env.encode_command(0.5, 0.0))  # straight along the corridor at 0.5 m/s
        if env.crowd.events and fired_at is None:
            fired_at = before  # the trigger is checked at the start of the step, on the robot's position then
            break
        np.testing.assert_allclose(env.crowd.pos[i], start, atol=0.05)  # standing still until then
    assert fired_at is not None and env.crowd.events[0]["kind"] == "start"
    d = math.hypot(*(fired_at - np.array(ped.trigger_point)))
    assert ped.trigger_within_m - 0.5 * 0.1 - 1e-6 <= d <= ped.trigger_within_m + 1e-6  # within one step of 3.0 m


def test_time_trigger_and_head_lead_before_a_scripted_turn():
    """crossing_turn: the walker starts when the robot has driven to its trigger distance, and its head turns
    toward the new direction lead_s before the walking direction follows."""
    env = _env("crossing_turn")
    _reset_facing_east(env, 0)
    i = env.crowd.n_random
    ped = load_scenario("crossing_turn").pedestrians[0]
    turn_dir = -math.pi / 2  # the turn across the robot's path: south
    head, walk = [], []
    for _k in range(120):
        env.step(env.encode_command(0.6, 0.0))  # straight along y = 4 at 0.6 m/s
        head.append(float(env.bodies.head_yaw[i]))
        walk.append(math.atan2(env.crowd.vel[i, 1], env.crowd.vel[i, 0]))
    events = [e for e in env.crowd.events if e["ped"] == i]
    assert [e["kind"] for e in events] == ["start", "turn"]
    travelled = math.hypot(*(np.array(ped.trigger_point) - np.array([1.5, 4.0]))) - ped.trigger_within_m
    assert events[0]["t_s"] == pytest.approx(travelled / 0.6, abs=0.25)  # fires at the distance asked
    t = np.arange(1, 121) * 0.1

    def first(series, within):
        return float(t[np.argmax(np.abs(wrap_angle(np.array(series) - turn_dir)) < within)])

    head_turned, walk_turned = first(head, math.radians(45)), first(walk, math.radians(45))
    assert events[1]["t_s"] < head_turned < walk_turned
    assert walk_turned - head_turned >= 0.5 * ped.lead_s  # the head leads the walking direction by about lead_s


@pytest.mark.parametrize("speed", [0.8, 0.9])
def test_crossing_turn_is_a_collision_course_for_a_robot_that_does_not_react(speed):
    """The walker's trigger times its turn to the robot: driving straight at a cruise speed, the robot hits the
    walker or grazes it (the scenario tests reacting to the turn, not only passing a parallel walker)."""
    env = _env("crossing_turn")
    _reset_facing_east(env, 0)
    done = False
    while not done:
        _, _, term, trunc, _ = env.step(env.encode_command(speed, 0.0))
        done = term or trunc
    m = scenario_metrics(env.trace(), env.crowd.scripted, env.crowd.events)
    assert m["min_clearance_scripted_m"] <= 0.1


def test_trials_differ_in_heading_and_walker_speed_within_the_jitter():
    env = _env("crossing_turn")
    sc = load_scenario("crossing_turn")
    seen = set()
    for seed in range(4):
        env.reset(seed=seed)
        assert abs(env.robot[2] - sc.start_yaw) <= sc.yaw_jitter + 1e-9
        v0 = float(env.crowd.v0[env.crowd.n_random])
        assert abs(v0 / sc.pedestrians[0].speed_mps - 1) <= sc.speed_jitter + 1e-9
        seen.add(round(v0, 6))
    assert len(seen) == 4


def test_scenario_episode_is_deterministic():
    runs = []
    for _ in range(2):
        env = _env("doorway")
        env.reset(seed=5)
        for _ in range(60):
            env.step(env.encode_command(0.6, 0.1))
        tr = env.trace()
        runs.append((tr.robot_pose, tr.ped_xy, tr.ped_head_yaw, list(env.crowd.events)))
    for a, b in zip(runs[0][:3], runs[1][:3], strict=True):
        np.testing.assert_array_equal(a, b)
    assert runs[0][3] == runs[1][3]


def test_scenario_metrics_collision_clearance_and_reaction():
    env = _env("head_on")
    _reset_facing_east(env, 0)
    done = False
    while not done:  # drive straight into the walker
        _, _, term, trunc, info = env.step(env.encode_command(0.6, 0.0))
        done = term or trunc
    tr = env.trace()
    m = scenario_metrics(tr, env.crowd.scripted, env.crowd.events)
    assert tr.outcome == "collision_pedestrian" and m["collision_scripted"] == 1.0
    assert m["min_clearance_scripted_m"] <= 0.0
    assert m["cue_onset_s"] == 0.0 and math.isnan(m["reaction_time_s"])  # never changed its command


def test_reaction_time_finds_the_first_command_that_opens_the_gap():
    env = _env("head_on")
    _reset_facing_east(env, 0)
    for k in range(60):  # straight for 3 s, then veer left (away from the walker, who keeps to y = 1.0-1.1)
        env.step(env.encode_command(0.6, 0.0 if k < 30 else 0.8))
    tr = env.trace()
    peds = np.nonzero(env.crowd.scripted)[0]
    assert reaction_time_s(tr, peds, 0.0) == pytest.approx(3.0)
    assert reaction_time_s(tr, peds, 1.0) == pytest.approx(2.0)
    assert math.isnan(reaction_time_s(tr, peds, 3.5))  # no change of command after the onset


def _drive(scenario: str, commands, **kw):
    env = _env(scenario, **kw)
    _reset_facing_east(env, 0)
    for v, w in commands:
        _, _, term, trunc, _ = env.step(env.encode_command(v, w))
        if term or trunc:
            break
    return env


def test_the_no_cue_twin_walks_the_same_without_the_head_lead():
    """``scenario_cues=False``: the scripted walker's path, timing and events are unchanged; only its head and torso
    no longer turn before its walking direction does."""
    straight = [(0.6, 0.0)] * 120
    cued, twin = _drive("crossing_turn", straight), _drive("crossing_turn", straight, scenario_cues=False)
    a, b = cued.trace(), twin.trace()
    np.testing.assert_array_equal(a.ped_xy, b.ped_xy)
    np.testing.assert_array_equal(a.robot_pose, b.robot_pose)
    assert cued.crowd.events == twin.crowd.events
    turn = next(e for e in cued.crowd.events if e["kind"] == "turn")
    k_turn, k_walk = round(turn["t_s"] / 0.1), round((turn["t_s"] + turn["lead_s"]) / 0.1)
    i = cued.crowd.n_random
    lead_gap = np.abs(wrap_angle(a.ped_head_yaw[k_turn + 2:k_walk, i] - b.ped_head_yaw[k_turn + 2:k_walk, i]))
    assert np.all(a.ped_head_yaw[:k_turn, i] == b.ped_head_yaw[:k_turn, i])
    assert lead_gap.max() > math.radians(30)  # the cued head looks across the robot's path, the twin's ahead


def test_cue_twin_metrics_find_the_first_command_the_cue_changed():
    """Two runs of head_on that agree until 3 s, then one veers away from the walker: the divergence is read from
    the commands alone, timed from the onset, and judged against the walker's recorded future."""
    same = [(0.6, 0.0)] * 30
    cued = _drive("head_on", same + [(0.6, 0.8)] * 30).trace()
    twin = _drive("head_on", same + [(0.6, 0.0)] * 30).trace()
    peds = np.array([0])
    m = cue_twin_metrics(cued, twin, peds, onset_s=2.5, lead_s=0.7)
    assert m["cue_divergence_s"] == pytest.approx(0.5) and m["cue_anticipated"] == 1.0
    assert m["cue_divergence_safer"] == 1.0 and m["twin_identical_before_cue"] == 1.0
    late = cue_twin_metrics(cued, twin, peds, onset_s=2.0, lead_s=0.7)
    assert late["cue_divergence_s"] == pytest.approx(1.0) and late["cue_anticipated"] == 0.0
    toward = cue_twin_metrics(twin, cued, peds, onset_s=2.5, lead_s=0.7)  # the straight run is the less safe one
    assert toward["cue_divergence_safer"] == 0.0
    before = cue_twin_metrics(cued, twin, peds, onset_s=4.0, lead_s=0.7)  # they differed before this onset
    assert before["twin_identical_before_cue"] == 0.0
    none = cue_twin_metrics(twin, twin, peds, onset_s=1.0, lead_s=0.7)
    assert math.isnan(none["cue_divergence_s"]) and none["cue_anticipated"] == 0.0 and math.isnan(
        none["cue_divergence_safer"])
