"""The baselines' shared sensors, sub-goal, checkpoints and their wiring into train / eval."""

import json
import math

import numpy as np
import pytest
import torch

from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from rl.baselines import BASELINES
from rl.baselines.common import (
    lidar_scan,
    load_baseline,
    save_baseline,
    to_robot_frame,
    tracked_pedestrians,
)
from sim.env import CrowdNavEnv
from sim.planners.global_path import GlobalPath, distance_to_polyline


@pytest.fixture()
def env():
    e = CrowdNavEnv(scene="open_crowd", density=0.0, obs_mode="state")
    e.reset(seed=0)
    return e


def _place(env, robot, peds=(), vel=(), radius=0.25):
    """Puts the robot and pedestrians at constructed places (a tiny crowd of ``len(peds)``)."""
    env.robot = np.array(robot, float)
    n = len(peds)
    env.crowd.n = n
    env.crowd.pos = np.array(peds, float).reshape(n, 2)
    env.crowd.vel = np.array(vel, float).reshape(n, 2)
    env.crowd.radius = np.full(n, radius)


def _open_spot(env):
    """A point of the open crowd scene with at least 3 m of free space around it."""
    lo, hi = np.array(env.spec_scene.bounds[0::2]), np.array(env.spec_scene.bounds[1::2])
    c = (lo + hi) / 2
    assert env.layout.clearance_at(c[None])[0] > 3.0
    return c


def test_lidar_sees_a_pedestrian_disc_at_its_surface(env):
    c = _open_spot(env)
    _place(env, [c[0], c[1], 0.0], peds=[[c[0] + 2.0, c[1]]], vel=[[0.0, 0.0]], radius=0.25)
    r = lidar_scan(env, 360, 2 * math.pi, 10.0)
    ang = -math.pi + (np.arange(360) + 0.5) * (2 * math.pi / 360)  # relative to the heading
    ahead = int(np.argmin(np.abs(ang)))
    assert r[ahead] == pytest.approx(1.75, abs=0.01)  # 2 m to the centre minus the radius
    behind = int(np.argmin(np.abs(np.abs(ang) - math.pi)))
    assert r[behind] > 2.5  # nothing behind within 3 m (open space)
    # the pedestrian subtends asin(0.25 / 2) on either side: rays beyond that do not see it
    hit = np.abs(ang) < math.asin(0.25 / 2.0) - 0.01
    miss = (np.abs(ang) > math.asin(0.25 / 2.0) + 0.02) & (np.abs(ang) < 0.5)
    assert np.all(r[hit] < 2.0) and np.all(r[miss] > 2.5)


def test_lidar_without_pedestrians_is_the_static_scan(env):
    c = _open_spot(env)
    _place(env, [c[0], c[1], 0.3])
    r = lidar_scan(env, 64, math.radians(270), 10.0)
    ang = 0.3 + np.linspace(-math.radians(135), math.radians(135), 64)
    ref = env.layout.geometry.raycast(np.array(c), ang, 10.0)
    np.testing.assert_allclose(r, np.minimum(ref, 10.0), atol=1e-5)


def test_tracks_are_in_the_robot_frame_within_range(env):
    c = _open_spot(env)
    _place(env, [c[0], c[1], math.pi / 2], peds=[[c[0], c[1] + 2.0], [c[0] + 9.0, c[1]]],
           vel=[[1.0, 0.0], [0.0, 0.0]])
    tr = tracked_pedestrians(env, 5.0)
    assert tr.shape == (1, 5)  # the far one is out of range
    np.testing.assert_allclose(tr[0], [2.0, 0.0, 0.0, -1.0, 0.25], atol=1e-6)  # ahead; moving to the robot's right
    np.testing.assert_allclose(to_robot_frame(env, np.array([c[0] - 1.0, c[1]])), [0.0, 1.0], atol=1e-6)


def test_global_path_subgoal_walks_the_lookahead_along_the_path():
    path = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 3.0]])
    d, k, q = distance_to_polyline(np.array([0.5, 0.2]), path)
    assert d == pytest.approx(0.2) and k == 0 and np.allclose(q, [0.5, 0.0])
    e = CrowdNavEnv(scene="corner", density=0.0, obs_mode="state")
    e.reset(seed=3)
    g = GlobalPath(lookahead_m=2.0)
    g.reset(e)
    sub = g.subgoal(e)
    assert np.hypot(*(sub - e.robot[:2])) <= 2.0 + 1e-6
    # the sub-goal is on a collision-free path: the segment robot -> sub-goal clears the walls
    assert e.layout.segments_min_clearance(e.robot[None, :2], sub[None])[0] > e.cfg.robot.radius_m
    # a near target is returned as is
    near = e.robot[:2] + 0.5 * np.array([math.cos(e.robot[2]), math.sin(e.robot[2])])
    if e.layout.clearance_at(near[None])[0] > 0.4:
        np.testing.assert_allclose(g.subgoal(e, near), near, atol=1e-6)


class _Tiny(torch.nn.Module):
    def __init__(self, width: int) -> None:
        super().__init__()
        self.lin = torch.nn.Linear(3, width)


def test_baseline_checkpoint_roundtrip_and_errors(tmp_path):
    torch.manual_seed(0)
    m = _Tiny(4)
    save_baseline(tmp_path / "b", "drl_vo", m, {"width": 4}, {"x": [3]}, {"ppo_steps": 10})
    back, desc = load_baseline(tmp_path / "b", "drl_vo", lambda net: _Tiny(net["width"]))
    assert desc["produced_by"] == {"ppo_steps": 10}
    assert torch.equal(back.lin.weight, m.lin.weight)
    with pytest.raises(CorruptArtifactError, match="expected a 'vint' baseline"):
        load_baseline(tmp_path / "b", "vint", lambda net: _Tiny(net["width"]))
    with pytest.raises(CorruptArtifactError, match="policy.safetensors"):
        load_baseline(tmp_path / "b", "drl_vo", lambda net: _Tiny(5))  # weights that do not fit
    (tmp_path / "b" / "policy.safetensors").write_bytes(b"garbage")
    with pytest.raises(CorruptArtifactError, match="policy.safetensors"):
        load_baseline(tmp_path / "b", "drl_vo", lambda net: _Tiny(net["width"]))
    with pytest.raises(InputMissingError, match="policy.json"):
        load_baseline(tmp_path / "none", "drl_vo", lambda net: _Tiny(4))


def test_baselines_are_train_variants_and_eval_methods(tmp_path):
    from evaluation.methods import available_methods, resolve_methods, spec_from_checkpoint
    from rl.stage import TRAIN_VARIANTS

    for name, info in BASELINES.items():
        assert name in TRAIN_VARIANTS and name in available_methods()
        with pytest.raises(InputMissingError, match=f"train --variant {name}"):
            resolve_methods([name], tmp_path)
        ckpt = tmp_path / "checkpoints" / "policy" / name
        save_baseline(ckpt, name, _Tiny(2), {"width": 2}, {}, {})
        (ckpt / "manifest.json").write_text("{}")
        (spec,) = resolve_methods([name], tmp_path)
        assert (spec.kind, spec.label, spec.obs_mode, spec.action_type) == ("baseline", info.label, info.obs_mode,
                                                                           info.action_type)
        assert spec_from_checkpoint(ckpt) == spec
    with pytest.raises(ConfigError, match="unknown method 'sarl'"):
        resolve_methods(["sarl"], tmp_path)


def test_report_states_each_methods_training_budget(tmp_path):
    from evaluation.report import report_markdown, training_budget

    ckpt = tmp_path / "drl_vo"
    save_baseline(ckpt, "drl_vo", _Tiny(2), {"width": 2}, {}, {"expert_episodes": 200, "ppo_steps": 50_000})
    (ckpt / "metrics.json").write_text(json.dumps({"train_seconds": 612.4}))
    b = training_budget(ckpt)
    rows = [{"method": "drl_vo", "scene": "office_lobby", "density": 0.1, "seed": s, "success": s % 2,
             "collision": 1 - s % 2, "timeout": 0, "nav_time_s": 8.0, "path_length_m": 6.0, "tpz_s": 1.0}
            for s in range(4)]
    md = report_markdown(rows, {"drl_vo": "DRL-VO"}, "# t", budgets={"drl_vo": b})
    assert "| DRL-VO | expert_episodes 200, ppo_steps 50000 | 612 |" in md


def test_train_cli_vint_without_a_dataset_is_one_clear_error(tmp_path, capsys):
    from pipeline import cli

    rc = cli.main(["train", "--profile", "smoke", "--data-dir", str(tmp_path), "--variant", "vint"])
    stderr = capsys.readouterr().err
    assert rc == 2, stderr
    err = [ln for ln in stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "icrowdnav/smoke" in err[0] and "make record" in err[0], stderr
    assert not (tmp_path / "checkpoints").exists()  # nothing written


def test_global_path_points_ahead_are_spaced_along_the_path():
    e = CrowdNavEnv(scene="corner", density=0.0, obs_mode="state")
    e.reset(seed=3)
    g = GlobalPath(lookahead_m=2.0)
    g.reset(e)
    g.path = np.array([e.robot[:2], e.robot[:2] + [1.0, 0.0], e.robot[:2] + [1.0, 3.0]])
    g.target = g.path[-1].copy()
    pts = g.ahead(e, [0.5, 1.0, 1.5, 3.0, 9.0], g.target) - e.robot[:2]
    np.testing.assert_allclose(pts, [[0.5, 0.0], [1.0, 0.0], [1.0, 0.5], [1.0, 2.0], [1.0, 3.0]], atol=1e-9)
    np.testing.assert_allclose(g.subgoal(e, g.target) - e.robot[:2], [1.0, 1.0], atol=1e-9)


def test_global_path_keeps_a_path_per_target_when_asked_for_two_alternately(monkeypatch):
    """A long-horizon run asks for the goal's and the current waypoint's path every step: the shared planner gives
    what one planner per target gives, and plans each target once while the robot stays on its path."""
    e = CrowdNavEnv(scene="corner", density=0.0, obs_mode="state")
    e.reset(seed=3)
    shared, own = GlobalPath(lookahead_m=2.0), {0: GlobalPath(lookahead_m=2.0), 1: GlobalPath(lookahead_m=2.0)}
    for g in (shared, *own.values()):
        g.reset(e)
    targets = [np.asarray(e.goal, float), e.robot[:2] + 0.4 * (np.asarray(e.goal, float) - e.robot[:2])]
    plans = []
    real = shared.nav.shortest_path
    monkeypatch.setattr(shared.nav, "shortest_path", lambda *a: plans.append(1) or real(*a))
    d = [0.5, 1.0, 2.0]
    for _ in range(5):  # the robot creeps along, both targets asked for at every step
        for k, t in enumerate(targets):
            np.testing.assert_array_equal(shared.ahead(e, d, t), own[k].ahead(e, d, t))
        e.robot[:2] += 0.05 * (targets[1] - e.robot[:2]) / np.hypot(*(targets[1] - e.robot[:2]))
    assert len(plans) == 2 + 2  # once per target by the shared planner (before: at every switch, 10) and by each own
