"""Failure causes of an eval run (evaluation.failures): the classification on constructed episodes, and a real tiny
run whose episodes time out — counted, drawn on their rebuilt layout, and the named errors."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from evaluation import failures
from evaluation.failures import analyse, classify, draw, hit_bearing, main, ped_hit_geometry
from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from sim.env import CameraConfig, CrowdNavEnv, SimConfig
from sim.geometry import Box, Cylinder, StaticGeometry
from sim.trace import EpisodeTrace


def _trace(outcome: str, ped_at: list[tuple[float, float]], v: float = 0.5, w: float = 0.8) -> EpisodeTrace:
    """A robot driving along +x for 10 steps to (1, 0), the goal at (5, 0), people standing at ``ped_at``."""
    t1, n = 11, len(ped_at)
    pose = np.stack([np.linspace(0.0, 1.0, t1), np.zeros(t1), np.zeros(t1)], -1)
    peds = np.repeat(np.asarray(ped_at, float).reshape(1, n, 2), t1, 0)
    return EpisodeTrace(dt_s=0.1, robot_radius_m=0.3, goal_radius_m=0.3, robot_pose=pose,
                        robot_cmd=np.tile([v, w], (t1 - 1, 1)), goal_xy=np.array([5.0, 0.0]),
                        start_xy=np.zeros(2), ped_xy=peds, ped_vel=np.zeros_like(peds), ped_radius=np.full(n, 0.25),
                        ped_yaw=np.zeros((t1, n)), ped_head_yaw=np.zeros((t1, n)), static_clearance_m=np.ones(t1),
                        outcome=outcome)


def test_obstacle_hits_are_split_by_the_nearest_person():
    near = classify(_trace("collision_obstacle", [(1.0, 1.0), (4.0, 0.0)]))  # 1 m - 0.25 - 0.3 = 0.45 m gap
    assert near["cause"] == "collision_obstacle_near_person" and near["nearest_person_m"] == pytest.approx(0.45)
    assert near["tail_speed_mps"] == pytest.approx(0.5) and near["tail_yaw_rate_radps"] == pytest.approx(0.8)
    assert classify(_trace("collision_obstacle", [(1.0, 3.0)]))["cause"] == "collision_obstacle_clear"
    assert classify(_trace("collision_obstacle", [(1.0, 1.0)]), near_m=0.4)["cause"] == "collision_obstacle_clear"
    assert classify(_trace("collision_obstacle", []))["cause"] == "collision_obstacle_clear"  # nobody there
    assert classify(_trace("collision_pedestrian", [(1.5, 0.0)]))["cause"] == "collision_pedestrian"
    late = classify(_trace("timeout", [(1.0, 3.0)]))
    assert late["cause"] == "timeout" and late["goal_distance_m"] == pytest.approx(4.0)
    with pytest.raises(ConfigError, match="not a failure"):
        classify(_trace("success", []))
    assert "frozen" not in late  # shorter than FROZEN_S: not judged


def test_a_timeout_that_ends_standing_still_is_frozen():
    """The last 10 s within 0.1 m of one spot: frozen — with people near for most of it, or nobody; a robot that
    still moves (here: 0.5 m back and forth) is not."""
    def standing(ped_at, sway_m=0.02):
        t1 = 150
        x = 1.0 + sway_m * np.sin(np.arange(t1) / 3.0)
        tr = _trace("timeout", ped_at)
        pose = np.stack([x, np.zeros(t1), np.zeros(t1)], -1)
        peds = np.repeat(np.asarray(ped_at, float).reshape(1, len(ped_at), 2), t1, 0)
        return replace(tr, robot_pose=pose, robot_cmd=np.zeros((t1 - 1, 2)), ped_xy=peds, ped_vel=np.zeros_like(peds),
                       ped_yaw=np.zeros((t1, len(ped_at))), ped_head_yaw=np.zeros((t1, len(ped_at))),
                       static_clearance_m=np.ones(t1))

    alone = classify(standing([(5.0, 3.0)]))
    assert alone["frozen"] and not alone["frozen_people_near"]
    crowded = classify(standing([(1.0, 1.0)]))
    assert crowded["frozen"] and crowded["frozen_people_near"]
    assert not classify(standing([], sway_m=0.25))["frozen"]


def test_the_bearing_of_a_hit_obstacle_is_measured_from_the_heading():
    class Layout:  # what hit_bearing reads of a SceneLayout
        geometry = StaticGeometry([Cylinder((1.0, 1.0), 0.2)])

    assert hit_bearing(Layout, np.array([1.0, 0.5, np.pi / 2])) == pytest.approx(0.0, abs=1e-6)  # dead ahead
    assert hit_bearing(Layout, np.array([1.0, 0.5, 0.0])) == pytest.approx(90.0)  # on its left
    assert hit_bearing(Layout, np.array([1.0, 0.5, np.pi])) == pytest.approx(-90.0)  # on its right
    assert abs(hit_bearing(Layout, np.array([1.0, 0.5, -np.pi / 2]))) == pytest.approx(180.0)  # behind


def test_a_pedestrian_hit_records_where_the_person_hit_was_and_who_closed_the_gap():
    """The robot of :func:`_trace` drives along +x at 1 m/s to (1, 0). A person standing just ahead is hit in view
    and the robot closed the gap; one walking into it from behind (+x at 2 m/s, ending 0.5 m behind it) was never in
    the 60-degree view and closed the gap himself; one who stepped in front of it at the last step is in view at
    contact; one ahead in the first three steps and beside it at contact was last seen 0.8 s before. The person hit is
    the nearest body, not the first column."""
    ahead = ped_hit_geometry(_trace("collision_pedestrian", [(4.0, 3.0), (1.5, 0.0)]), view_deg=60.0, tail_s=0.5)
    assert ahead["ped_hit_bearing_deg"] == pytest.approx(0.0) and ahead["ped_hit_in_view"]
    assert ahead["ped_last_in_view_s_before"] == 0.0
    assert ahead["closing_robot_mps"] == pytest.approx(1.0) and ahead["closing_ped_mps"] == pytest.approx(0.0)

    tr = _trace("collision_pedestrian", [(0.0, 0.0)])
    behind = replace(tr, ped_xy=(tr.robot_pose[:, :2] + np.array([-0.5, 0.0]) - np.linspace(1.0, 0.0, 11)[:, None]
                                 * np.array([1.0, 0.0]))[:, None])
    rear = ped_hit_geometry(behind, view_deg=60.0, tail_s=0.5)
    assert abs(rear["ped_hit_bearing_deg"]) == pytest.approx(180.0) and not rear["ped_hit_in_view"]
    assert rear["ped_last_in_view_s_before"] is None
    assert rear["closing_robot_mps"] == pytest.approx(-1.0) and rear["closing_ped_mps"] == pytest.approx(2.0)

    side = np.repeat(np.array([[[1.0, 1.0]]]), 11, 0)  # beside the robot, then in front of it at contact
    side[-1, 0] = (1.5, 0.0)
    cut = ped_hit_geometry(replace(tr, ped_xy=side), view_deg=60.0, tail_s=0.1)
    assert cut["ped_hit_in_view"] and cut["ped_last_in_view_s_before"] == 0.0
    assert cut["closing_robot_mps"] == pytest.approx(1.0)
    early = np.repeat(np.array([[[0.5, 1.0]]]), 11, 0)  # ahead in the first 3 steps, then beside and behind it
    early[:3, 0] = (3.0, 0.0)
    early[-1, 0] = (1.0, 0.5)
    gone = ped_hit_geometry(replace(tr, ped_xy=early), view_deg=60.0, tail_s=0.5)
    assert not gone["ped_hit_in_view"] and gone["ped_last_in_view_s_before"] == pytest.approx(0.8)


def test_a_straight_line_through_an_obstacle_is_blocked_once_per_scene_seed(monkeypatch):
    """The robot of :func:`_trace` starts at (0, 0) with its goal at (5, 0): a shelf across (2.5, 0) blocks the line,
    the same shelf 1 m aside does not; the layout is looked up once per cell and scene seed."""
    class FakeLayouts:
        scene_seeds = {1: 100, 2: 100, 3: 101}

        def __init__(self, box):
            self.geometry, self.calls = StaticGeometry([box]), 0

        def layout(self, row, trace):
            self.calls += 1
            return self

    monkeypatch.setattr(failures, "_load_trace", lambda path: _trace("timeout", [(9.0, 9.0)]))
    rows = [{"scene": "warehouse", "density": 0.1, "seed": k, "method": "full"} for k in (1, 2, 3)]
    across, aside = FakeLayouts(Box((2.5, 0.0), (0.4, 3.0))), FakeLayouts(Box((2.5, 1.0), (0.4, 0.5)))
    for lay, want in ((across, True), (aside, False)):
        cache = {}
        assert [failures.line_blocked(Path("run"), r, lay, cache) for r in rows] == [want] * 3
        assert lay.calls == 2  # seeds 1 and 2 share scene seed 100


def test_a_timeouts_view_holds_its_start_and_goal_a_hits_stays_around_the_end():
    trace = replace(_trace("timeout", []), goal_xy=np.array([9.0, -1.0]))  # the robot stopped at (1, 0)
    assert failures.view_bounds(trace, whole_span=False) == pytest.approx((-2.0, 4.0, -3.0, 3.0))
    assert failures.view_bounds(trace, whole_span=True) == pytest.approx((-2.0, 10.0, -3.0, 3.0))


def _analysed(run: str, outcomes: list[tuple[int, bool, bool]], method: str = "full",
              ped_hits: dict[int, bool] | None = None) -> dict:
    """What :func:`analyse` returns of a run, reduced to its episodes: (seed, success, line blocked) each, and its
    pedestrian hits: seed -> the person hit was in view."""
    cell = {"method": method, "scene": "warehouse", "density": 0.1}
    return {"run": run, "episodes": [{**cell, "seed": seed, "success": int(ok), "line_blocked": line}
                                     for seed, ok, line in outcomes],
            "failures": [{**cell, "seed": seed, "cause": "collision_pedestrian", "ped_hit_in_view": v}
                         for seed, v in (ped_hits or {}).items()]}


def test_two_runs_are_paired_where_the_line_is_blocked_and_where_it_is_clear():
    """Seeds 0-3 need a detour, 4-9 do not; the run gains two detours and loses one open episode against its base.
    Its pedestrian hits pair too: the base hit a person in view at seed 0 and one out of view at seed 8, the run
    people in view at seeds 2, 7 and 8."""
    line = [s < 4 for s in range(10)]
    base = _analysed("base", [(s, ok, line[s]) for s, ok in enumerate([0, 0, 0, 1, 1, 1, 1, 1, 0, 1])],
                     ped_hits={0: True, 8: False})
    run = _analysed("run", [(s, ok, line[s]) for s, ok in enumerate([1, 1, 0, 1, 1, 1, 1, 0, 0, 1])], "no_bev",
                    ped_hits={2: True, 7: True, 8: True})
    res = failures.paired_by_line(run, base)
    blocked, clear, total = (res["groups"][k] for k in ("line blocked", "line clear", "all"))
    assert (blocked["n"], blocked["sr_base"], blocked["sr_run"], blocked["a_only"], blocked["b_only"]) == (
        4, 0.25, 0.75, 0, 2)
    assert (clear["n"], clear["a_only"], clear["b_only"]) == (6, 1, 0) and clear["p_value"] == pytest.approx(1.0)
    assert (total["n"], total["a_only"], total["b_only"]) == (10, 1, 2)
    table = failures.paired_markdown(res)
    assert "| line blocked | 4 | 0.250 | 0.750 | 0 / 2 | 0.5 |" in table and "Paired with base" in table
    seen, unseen = res["ped_hits"]["person in view"], res["ped_hits"]["person out of view"]
    assert (seen["a_only"], seen["b_only"], unseen["a_only"], unseen["b_only"]) == (1, 3, 1, 0)
    assert "| person in view | 1 / 3 | 0.625 |" in table
    with pytest.raises(InputMissingError, match=r"1 episodes have no pair .*\('warehouse', 0.1, 9\)"):
        failures.paired_by_line(_analysed("run", [(s, 1, line[s]) for s in range(9)]), base)
    with pytest.raises(CorruptArtifactError, match=r"blocked in one run's layout and clear in the other's"):
        failures.paired_by_line(_analysed("run", [(s, 1, not line[s]) for s in range(10)]), base)
    two = {"run": "two", "episodes": run["episodes"] + base["episodes"]}
    with pytest.raises(ConfigError, match=r"needs one method, the run holds \['full', 'no_bev'\]"):
        failures.paired_by_line(two, base)


@pytest.fixture(scope="module")
def timed_out_run(tmp_path_factory):
    """The expert with a 2 s time limit in the lobby: both episodes time out (real failures, real traces)."""
    from evaluation.stage import EvalConfig
    from pipeline.verbs.eval import run

    data = tmp_path_factory.mktemp("data")
    sim = SimConfig(max_episode_s=2.0, timeout_s_per_m=0.0,
                    camera=replace(SimConfig().camera, width_px=64, height_px=48))
    run(EvalConfig(data_dir=str(data), methods=["expert"], scenes=["office_lobby"], densities=[0.1], goals=1,
                   trials=2, routing_scenes=[], scenarios=[], workers=1, figures=0, videos=0, sim=sim, progress=False,
                   long_horizon=replace(EvalConfig().long_horizon, runs=0)))
    return data / "eval" / "benchmark"


@pytest.mark.slow
def test_a_real_run_is_counted_and_drawn_on_its_rebuilt_layout(timed_out_run, tmp_path):
    res = analyse(timed_out_run)
    counts = res["counts"]["expert"]["office_lobby@0.1"]
    assert {k: counts[k] for k in ("episodes", "timeout", "successes", "line_blocked_successes")} == {
        "episodes": 2, "timeout": 2, "successes": 0, "line_blocked_successes": 0}
    assert counts["line_blocked"] == 0  # this goal's straight line is clear (both trials share it)
    assert [f["cause"] for f in res["failures"]] == ["timeout", "timeout"]
    assert all(f["goal_distance_m"] > 0.3 and f["steps"] == 20 for f in res["failures"])
    (png,) = draw(timed_out_run, res, tmp_path, per_cause=1)
    assert png == tmp_path / "figures" / "timeout_0.png" and png.stat().st_size > 10_000


@pytest.mark.slow
def test_cli_writes_its_tables_and_refuses_bad_input(timed_out_run, tmp_path, capsys):
    out = tmp_path / "f"
    assert main([str(timed_out_run), "--figures", "0", "--out", str(out)]) == 0
    assert "| expert | office_lobby@0.1 | 2 | 0 | 0 | 0 | 2 | 0 | 0 | 0 | — (0) / 0.00 (2) |" in capsys.readouterr().out
    assert json.loads((out / "failures.json").read_text())["counts"]["expert"]["office_lobby@0.1"]["timeout"] == 2
    assert main([str(tmp_path / "nope")]) == 2
    assert "no per-episode rows" in capsys.readouterr().err
    assert main([str(timed_out_run), "--method", "dwa", "--out", str(tmp_path / "g")]) == 2
    assert "no episode of method 'dwa'" in capsys.readouterr().err and not (tmp_path / "g").exists()
    assert main([str(timed_out_run), "--replay", "1", "--workers", "0", "--out", str(tmp_path / "h")]) == 2
    assert "--workers: expected an integer >= 1, got 0" in capsys.readouterr().err and not (tmp_path / "h").exists()
    assert main([str(timed_out_run), "--figures", "0", "--out", str(tmp_path / "i"), "--method", "expert",
                 "--against", f"{timed_out_run}:expert"]) == 0
    assert "| line clear | 2 | 0.000 | 0.000 | 0 / 0 | — |" in capsys.readouterr().out
    assert json.loads((tmp_path / "i" / "failures.json").read_text())["against"]["groups"]["all"]["n"] == 2


@pytest.mark.slow
def test_a_trace_that_does_not_match_todays_layout_is_a_named_error(timed_out_run, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(timed_out_run, run)
    seeds = json.loads((run / "seeds.json").read_text())
    for e in seeds["benchmark"]["episodes"]:
        e["scene_seed"] = int(e["scene_seed"]) + 7  # another goal: another start and goal than the trace's
    (run / "seeds.json").write_text(json.dumps(seeds))
    with pytest.raises(CorruptArtifactError, match="start and goal"):
        draw(run, analyse(run), tmp_path / "out", per_cause=1)


def _straight_teacher(data, sim, obs_contact=0.0):
    """A lookahead teacher whose cost only wants speed (straight ahead at full speed, whatever is in the way; with
    ``obs_contact`` < 0 also away from arcs its scan predicts to touch an obstacle), saved as
    ``checkpoints/policy/teacher`` with its manifest."""
    import torch

    from pipeline.core.manifest import Manifest, hash_tree
    from rl.lookahead import LINEAR_TERMS, N_LINEAR
    from rl.policy import build_policy, describe, save_policy
    from rl.teacher import teacher_net

    env = CrowdNavEnv(config=replace(sim, obs_mode="privileged", action_type="discrete"))
    space = env.observation_space
    env.close()
    net = teacher_net({"encoder": "lookahead"}, sim)
    policy = build_policy("teacher", None, space, net)
    head = policy.features_extractor.lookahead
    with torch.no_grad():
        for p in head.parameters():
            p.zero_()
        head.linear.weight[0, N_LINEAR - 2:] = torch.tensor([1.0, -0.5])  # + speed, - turning
        head.linear.weight[0, LINEAR_TERMS.index("obs_contact")] = obs_contact
    ck = data / "checkpoints" / "policy" / "teacher"
    save_policy(ck, policy, describe("teacher", None, space, net))
    (ck / "config.yaml").write_text("seed: 0\n")
    Manifest(stage="train", params={}, config_hash="0" * 64, seed=0, outputs=hash_tree(ck)).write(ck / "manifest.json")


@pytest.mark.slow
def test_replay_finds_a_hit_the_policy_predicted_and_the_shield_prevents_it(tmp_path):
    """A teacher that drives straight into the lobby's clutter: its obstacle hits replay exactly, each one an arc it
    predicted to touch while turning on the spot was free; the same checkpoint evaluated with ``shield_s`` on the
    same seeds hits no obstacle."""
    from evaluation.failures import replay_hits
    from evaluation.stage import EvalConfig
    from pipeline.verbs.eval import run

    sim = SimConfig(max_episode_s=12.0, timeout_s_per_m=0.0)
    _straight_teacher(tmp_path, replace(sim, scene="office_lobby"))

    def evaluate(name, shield):
        run(EvalConfig(data_dir=str(tmp_path), methods=["teacher"], scenes=["office_lobby"], densities=[0.05],
                       goals=3, trials=1, routing_scenes=[], scenarios=[], workers=1, figures=0, videos=0, sim=sim,
                       progress=False, paired_with="teacher", shield_s=shield, run_name=name,
                       long_horizon=replace(EvalConfig().long_horizon, runs=0)))
        return tmp_path / "eval" / name

    plain = evaluate("plain", None)
    res = analyse(plain)
    hits = [f for f in res["failures"] if f["cause"].startswith("collision_obstacle")]
    assert hits, res["failures"]
    replays = replay_hits(plain, res, len(hits))
    assert all(r["reproduced"] and r["chose_predicted_contact"] for r in replays)
    assert all(r["clearance_error_m"] < 0.05 for r in replays)  # the privileged scan: prediction = truth
    assert replay_hits(plain, res, len(hits), workers=2) == replays  # a pool replays the same, in order
    # --teacher with the run's own teacher: in every state it labels exactly what the policy chose, with the
    # policy's own probability, so none of its contact choices is one the teacher would have avoided
    labelled = replay_hits(plain, res, len(hits), teacher=True)
    for r in labelled:
        assert r["contact_choices"] > 0 and r["teacher_free_at_contact_choices"] == 0
        for st in r["steps"]:
            assert st["teacher_action"] == st["action"]
            assert st["teacher_p_chosen"] == pytest.approx(st["policy_p_chosen"], abs=1e-6)
            assert st["teacher_predicted_m"] == st["predicted_m"]
            assert st["empty_crowd_predicted_m"] == st["predicted_m"]  # its cost reads no pedestrian term
    shielded = analyse(evaluate("shielded", 0.6))
    assert not [f for f in shielded["failures"] if f["cause"].startswith("collision_obstacle")]


def _step(tracked, ped_m, free_m):
    return {"tracked": tracked, "ped_predicted_m": ped_m, "best_free_m": free_m}


def test_a_pedestrian_hit_is_classed_by_what_the_policy_perceived_and_chose():
    from evaluation.failures import ped_hit_class

    assert ped_hit_class([_step(True, 0.2, 0.5), _step(False, 0.2, 0.5)]) == "untracked"  # lost at the end
    assert ped_hit_class([]) == "untracked"
    assert ped_hit_class([_step(False, 0.3, 0.5), _step(True, -0.1, 0.2)]) == "chose_predicted_contact"
    assert ped_hit_class([_step(True, -0.1, -0.05), _step(True, -0.2, -0.1)]) == "no_free_arc"
    assert ped_hit_class([_step(True, 0.1, 0.5), _step(True, 0.05, 0.4)]) == "predicted_clear"


@pytest.mark.slow
def test_replay_of_pedestrian_hits_finds_the_person_tracked_and_the_contact_chosen(tmp_path):
    """The straight-driving teacher in a dense lobby runs into people: each pedestrian hit replays exactly, the
    privileged tracks hold the hit person at every step (the teacher's ``peds`` are the truth), and where an arc
    free of everyone existed the teacher chose one predicted to touch; the markdown counts them per class."""
    from evaluation.failures import PED_HIT_CLASSES, ped_replay_markdown, replay_hits
    from evaluation.stage import EvalConfig
    from pipeline.verbs.eval import run

    sim = SimConfig(max_episode_s=12.0, timeout_s_per_m=0.0)
    _straight_teacher(tmp_path, replace(sim, scene="office_lobby"))
    run(EvalConfig(data_dir=str(tmp_path), methods=["teacher"], scenes=["office_lobby"], densities=[0.4], goals=6,
                   trials=1, routing_scenes=[], scenarios=[], workers=1, figures=0, videos=0, sim=sim, progress=False,
                   paired_with="teacher", run_name="dense", long_horizon=replace(EvalConfig().long_horizon, runs=0)))
    out = tmp_path / "eval" / "dense"
    res = analyse(out, scene="office_lobby")
    hits = [f for f in res["failures"] if f["cause"] == "collision_pedestrian"]
    assert hits, res["failures"]
    out_of_view = sum(c.get("ped_hits_out_of_view", 0) for c in res["counts"]["teacher"].values())
    assert out_of_view == sum(not f["ped_hit_in_view"] for f in hits)  # where each person hit was, from the trace
    assert all(f["ped_hit_in_view"] == (f["ped_last_in_view_s_before"] == 0.0) for f in hits)
    assert any(f["closing_robot_mps"] + f["closing_ped_mps"] > 0.0 for f in hits)
    in_view = sum(f["ped_hit_in_view"] for f in hits)
    assert f"| teacher | {len(hits)} | {in_view} | " in failures.ped_hit_markdown(res)
    replays = replay_hits(out, res, len(hits), pedestrian=True)
    assert len(replays) == len(hits)
    for r in replays:
        assert r["reproduced"] and r["class"] in PED_HIT_CLASSES and r["class"] != "untracked"
        assert all(s["tracked"] and s["track_error_m"] < 0.05 for s in r["steps"])  # privileged tracks: the truth
        assert r["last_tracked_s_before"] == pytest.approx(0.0)
    assert any(r["class"] == "chose_predicted_contact" for r in replays)
    assert f"| teacher | {len(replays)} |" in ped_replay_markdown(replays)
    with pytest.raises(InputMissingError, match="no episode of scene 'warehouse'"):
        analyse(out, scene="warehouse")


def test_replay_reads_the_depth_scan_of_an_mlp_student_and_refuses_its_pedestrian_hits(tmp_path):
    """A student with the paper's MLP head predicts no clearances: its obstacle hits replay with each chosen arc's
    clearance to the depth scan its driver then perceives (what its obstacle shield reads). One that drives straight
    at full speed hits the lobby's clutter: the replays end as the run's rows did, the scan showed the contact coming
    while turning on the spot was free, and its clearances match the true ones (median); asking it for pedestrian
    clearances is one named error."""
    from evaluation.failures import replay_head, replay_hits, replay_markdown
    from evaluation.methods import resolve_methods
    from evaluation.stage import EvalConfig
    from pipeline.core.manifest import Manifest, hash_tree
    from pipeline.verbs.eval import run
    from tests.rl.helpers_mlp import save_mlp_student

    sim = SimConfig(max_episode_s=12.0, timeout_s_per_m=0.0, camera=CameraConfig(width_px=64, height_px=48))
    env = CrowdNavEnv(config=replace(sim, scene="office_lobby", obs_mode="visual", action_type="discrete"))
    _, info = env.reset(seed=0)
    env.close()
    ck = save_mlp_student(tmp_path / "checkpoints" / "policy" / "no_bev", info, straight_bias=100.0)
    Manifest(stage="train", params={}, config_hash="0" * 64, seed=0, outputs=hash_tree(ck)).write(ck / "manifest.json")
    run(EvalConfig(data_dir=str(tmp_path), methods=["no_bev"], scenes=["office_lobby"], densities=[0.05], goals=3,
                   trials=1, routing_scenes=[], scenarios=[], cue_twins=[], workers=1, figures=0, videos=0, sim=sim,
                   progress=False, paired_with="no_bev", run_name="mlp",
                   long_horizon=replace(EvalConfig().long_horizon, runs=0)))
    out = tmp_path / "eval" / "mlp"
    res = analyse(out)
    hits = [f for f in res["failures"] if f["cause"].startswith("collision_obstacle")]
    assert hits, res["failures"]
    replays = replay_hits(out, res, len(hits))
    assert all(r["reproduced"] for r in replays)
    assert any(r["chose_predicted_contact"] for r in replays)
    # the scan against the true distance to the static obstacles: equal, except where depth points that are not a
    # static obstacle (a person's body) lie nearer (one of the three hits here)
    assert np.median([r["clearance_error_m"] for r in replays]) < 0.05, replays
    assert f"Replayed obstacle hits: {len(replays)} ({len(replays)} reproduced)" in replay_markdown(replays)
    # --teacher: none in the data dir is one named error before any episode; with a teacher that avoids predicted
    # contacts, the student's contact choices are ones it would not have made (its own arc free, the student's
    # choice improbable to it); --other with the student itself chooses as the student does
    with pytest.raises(InputMissingError, match="teacher"):
        replay_hits(out, res, len(hits), teacher=True)
    with pytest.raises(ConfigError, match="--other: expected with --teacher"):
        replay_hits(out, res, len(hits), other="no_bev")
    _straight_teacher(tmp_path, replace(sim, scene="office_lobby"), obs_contact=-50.0)
    with pytest.raises(ConfigError, match=r"--other: 'teacher' reads \['odom', 'path'"):
        replay_hits(out, res, len(hits), teacher=True, other="teacher")  # inputs the student does not have
    labelled = replay_hits(out, res, len(hits), teacher=True, other="no_bev")

    def plain(r):  # a labelled replay without the teacher's keys: the teacher observes, it does not act
        return {**{k: r[k] for k in replays[0]}, "steps": [{k: st[k] for k in replays[0]["steps"][0]}
                                                           for st in r["steps"]]}

    assert [plain(r) for r in labelled] == replays
    bad = [st for r in labelled for st in r["steps"] if st["predicted_m"] < 0.0 < st["best_available_m"]]
    assert bad and sum(r["contact_choices"] for r in labelled) == len(bad)
    assert sum(st["teacher_predicted_m"] >= 0.0 for st in bad) >= 0.8 * len(bad)
    assert max(st["teacher_p_chosen"] for st in bad) < 0.05 < min(st["policy_p_chosen"] for st in bad)
    for st in (st for r in labelled for st in r["steps"]):
        assert st["other_predicted_m"] == st["predicted_m"]  # the same student in the same states
        assert st["empty_crowd_predicted_m"] == st["predicted_m"]  # its straight bias outweighs any pose
    assert f"| no_bev | {sum(r['contact_choices'] > 0 for r in labelled)} | {len(bad)} |" in replay_markdown(labelled)
    (spec,) = resolve_methods(["no_bev"], tmp_path, None)
    with pytest.raises(ConfigError, match="--replay-peds: method 'no_bev' has no predicted pedestrian clearances"):
        replay_head(spec, sim, pedestrian=True)
