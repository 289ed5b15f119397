"""SARL*-OM: joint state, angular map, danger-zone reward, learning a trivial scene, checkpoint round trip."""

import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from pipeline.core.errors import ConfigError, CorruptArtifactError
from rl.baselines import sarl_om as S
from rl.stage import TrainConfig
from rl.teacher import CurriculumStage
from sim.env import CrowdNavEnv, SimConfig

ROOT = Path(__file__).resolve().parents[3]
EMPTY_ROOM = {"name": "empty_room", "split": "train", "description": "test: an empty 6 x 6 m room",
              "bounds": [0.0, 6.0, 0.0, 6.0], "obstacles": [], "start_goal": {"distance_m": [1.0, 1.3],
                                                                              "clearance_m": 0.5}}
OC = S.Config()


def _scene(goal=(3.0, 0.0), humans=(), hits=(), speed=0.0) -> S.Scene:
    return S.Scene(goal=np.asarray(goal, float), humans=np.asarray(humans, float).reshape(-1, 5),
                   hits=np.asarray(hits, float).reshape(-1, 2),
                   speed=speed, radius=0.3, v_pref=1.0, goal_radius=0.3)


def test_joint_state_is_crowdnav_rotate():
    """Goal straight to the left (+y): the goal frame is the robot frame turned by +90°."""
    human = [[1.0, 2.0, 0.5, 0.0, 0.25]]  # robot frame: 1 m ahead, 2 m left, walking forward
    sc = _scene(goal=(0.0, 3.0), humans=human, speed=0.8)
    js = S.current_state(sc, OC)
    np.testing.assert_allclose(js["self"][0], [3.0, 1.0, -math.pi / 2, 0.3, 0.0, -0.8], atol=1e-6)
    # in the goal frame x' = y, y' = -x
    np.testing.assert_allclose(js["humans"][0, 0], [2.0, -1.0, 0.0, -0.5, 0.25, math.sqrt(5), 0.55], atol=1e-6)
    assert js["mask"][0].tolist() == [1.0] + [0.0] * (OC.max_humans - 1)
    assert not js["humans"][0, 1:].any()


def test_angular_map_of_a_wall_and_its_scan():
    """A wall 1 m ahead across the robot's path: the sectors straight ahead are the closest, the rear is free."""
    scene = {"name": "wall", "split": "train", "description": "test: a wall", "bounds": [0.0, 8.0, 0.0, 8.0],
             "obstacles": [{"box": {"center": [5.1, 4.0], "size": [0.2, 6.0]}}],
             "start_goal": {"distance_m": [1.0, 1.3], "clearance_m": 0.5}}
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "wall.yaml"
        path.write_text(yaml.safe_dump(scene))
        env = CrowdNavEnv(config=replace(SimConfig(), scene=str(path), density=0.0, obs_mode="state"))
        env.reset(seed=0)
        env.robot = np.array([4.0, 4.0, 0.0])  # wall face at x = 5.0: 1 m ahead
        env.goal = np.array([6.5, 4.0])  # behind the wall, straight ahead
        sc = S.perceive(env, None, OC)
    assert np.abs(sc.hits[:, 0] - 1.0).max() < 1e-3  # every hit is on the wall face
    om = S.current_state(sc, OC)["om"][0]
    ahead = OC.om_sectors // 2  # sector starting at angle 0 (goal direction)
    assert om[ahead] == pytest.approx(1 - 1.0 / OC.om_range_m, abs=1e-3)
    assert om.argmax() in (ahead - 1, ahead)  # the nearest sectors border the goal direction
    assert not om[: OC.om_sectors // 4].any() and not om[-OC.om_sectors // 4 + 1:].any()  # behind: free
    # the lookahead's collision test sees the wall
    r, done = S.reward(sc, np.array([[0.75, 0.0], [0.0, 0.0]]), np.zeros((0, 2)), 2.5, 0.1, OC)
    assert done.tolist() == [True, False] and r[0] == OC.collision_penalty


def test_value_is_finite_without_humans_and_permutation_invariant():
    torch.manual_seed(0)
    model = S.SarlOMValue(OC.om_sectors).eval()
    rng = np.random.default_rng(0)
    humans = np.c_[rng.uniform(-3, 3, (5, 2)), rng.uniform(-1, 1, (5, 2)), np.full(5, 0.25)]
    hits = rng.uniform(-3, 3, (40, 2))
    a = S.current_state(_scene(humans=humans, hits=hits, speed=0.5), OC)
    b = S.current_state(_scene(humans=humans[::-1], hits=hits, speed=0.5), OC)
    empty = S.current_state(_scene(hits=hits), OC)
    with torch.no_grad():
        va, vb, ve = (model(*S._tensors(x)).item() for x in (a, b, empty))
    assert va == pytest.approx(vb, abs=1e-5)
    assert math.isfinite(ve)
    # padding: the network on the present humans only (the lookahead's shortcut) gives the same value
    short = {**a, "humans": a["humans"][:, :5], "mask": a["mask"][:, :5]}
    with torch.no_grad():
        assert model(*S._tensors(short)).item() == pytest.approx(va, abs=1e-5)


def test_danger_zone_in_front_of_a_fast_walker_not_behind():
    walker = [[0.0, 0.0, 1.3, 0.0, 0.25]]  # at the origin, walking +x at 1.3 m/s
    sc = _scene(goal=(0.0, 5.0), humans=walker)
    front, back = np.array([[1.2, 0.0]]), np.array([[-1.2, 0.0]])
    depth = S.danger_depth(np.stack([front, back]), np.array([[1.3, 0.0]]), np.array([0.25]), 0.3, OC)
    assert depth[0, 0] > 0.3 and depth[1, 0] == 0.0
    (r_front,), _ = S.reward(sc, front, sc.humans[:, :2], 5.14, 0.1, replace(OC, progress_weight=0.0))
    (r_back,), _ = S.reward(sc, back, sc.humans[:, :2], 5.14, 0.1, replace(OC, progress_weight=0.0))
    assert r_front < 0.0 and r_back == 0.0
    # a standing human's zone is a small full circle (every side, 0.75 m reach); a walker's is a narrow long sector
    sides = np.array([[[0.7, 0.0]], [[-0.7, 0.0]], [[0.0, 0.7]], [[0.0, 1.0]]])
    still = S.danger_depth(sides, np.zeros((1, 2)), np.array([0.25]), 0.3, OC)[:, 0]
    walking = S.danger_depth(sides, np.array([[1.3, 0.0]]), np.array([0.25]), 0.3, OC)[:, 0]
    assert (still[:3] > 0).all() and still[3] == 0.0
    assert walking[0] > still[0] and walking[1] == walking[2] == 0.0


def test_config_validation():
    with pytest.raises(ConfigError, match="sarl_om.max_humans"):
        replace(OC, max_humans=0).validate()
    with pytest.raises(ConfigError, match="epsilon"):
        replace(OC, epsilon_start=0.1, epsilon_end=0.5).validate()


def _success_rate(model, oc, sim_cfg, seeds) -> tuple[float, list[int]]:
    env = CrowdNavEnv(config=replace(sim_cfg, obs_mode="state", action_type="discrete", info_level="basic"))
    wins = 0
    actions = []
    for s in seeds:
        ep = S._episode(env, model, oc, s, 0.0)
        wins += ep["outcome"] == "success"
        actions.append(ep["actions"])
    return wins / len(seeds), actions


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A SARL*-OM imitation-trained on an empty room (40 short expert episodes, 60 epochs; no RL iteration: a
    handful of TD updates on so little data measurably unsettles the value, see the report)."""
    tmp = tmp_path_factory.mktemp("sarl_om")
    scene = tmp / "empty_room.yaml"
    scene.write_text(yaml.safe_dump(EMPTY_ROOM))
    sim_cfg = replace(SimConfig(), scene=str(scene), density=0.0, max_episode_s=5.0)
    cfg = TrainConfig(variant="sarl_om", sim=sim_cfg, workers=1, threads=1, progress=False, seed=0)
    cfg.teacher.curriculum = [CurriculumStage(until=1.0, scenes=[str(scene)], densities=[0.0])]
    cfg.teacher.bc_episodes = 40
    cfg.sarl_om = replace(S.Config(), il_epochs=60, rl_iterations=0, episodes_per_iter=2, train_batches=10,
                          target_update_episodes=2, checkpoint_every=1)

    class Log:
        rows: list = []

        def add(self, phase, step, **values):
            self.rows.append((phase, step, values))

    log = Log()
    summary = S.train(cfg, tmp / "sarl_om", log)
    return tmp / "sarl_om", sim_cfg, summary, log


def test_learns_a_trivial_scene(trained):
    """After training the lookahead reaches a 1 m goal in an empty room on every seed, and its value alone ranks
    the states of a straight approach by their distance to the goal (an untrained net does not).

    Measured: SR 1.0 on 6 seeds; with 4-10 expert episodes and no RL it is 0.0-0.3 (the value's dependence on
    heading and speed is then wrong), so this fails when imitation does not work. An untrained net also reaches
    this goal (the lookahead's progress term steers it in an empty room), hence the value check."""
    ckpt, sim_cfg, summary, log = trained
    oc = replace(S.Config(), **{k: v for k, v in json.loads((ckpt / "policy.json").read_text())["config"].items()})
    model = S.Driver(ckpt).model
    after, _ = _success_rate(model, oc, sim_cfg, list(range(100, 106)))
    assert after >= 0.9, after

    def approach(net) -> np.ndarray:
        return np.array([net(*S._tensors(S.current_state(_scene(goal=(d, 0.0), speed=0.5), oc))).item()
                         for d in (0.5, 1.0, 2.0)])

    with torch.no_grad():
        v = approach(model)
        torch.manual_seed(1)
        v0 = approach(S.SarlOMValue(oc.om_sectors).eval())
    assert v[0] > v[1] > v[2] and v[0] - v[2] > 0.05, v
    assert not (v0[0] - v0[2] > 0.05), v0
    b = summary["budget"]
    assert b["expert_episodes"] == 40 and b["rl_episodes"] == 0
    assert {p for p, _, _ in log.rows} == {"imitation"}
    assert (ckpt / "rl" / "state.pt").is_file() and (ckpt / "rl" / "replay.npz").is_file()


def test_driver_in_a_fresh_process_reproduces_the_actions(trained, tmp_path):
    ckpt, sim_cfg, _, _ = trained

    def drive() -> list[int]:
        env = CrowdNavEnv(config=replace(sim_cfg, obs_mode="privileged", action_type="discrete"))
        drv = S.Driver(ckpt)
        obs, _ = env.reset(seed=123)
        drv.reset(env, obs)
        acts = []
        for _ in range(15):
            a = drv.act(env, obs)
            acts.append(a)
            obs, _, term, trunc, _ = env.step(a)
            if term or trunc:
                break
        assert drv.bev_panel().shape == (32, S.Config().om_sectors)
        return acts

    mine = drive()
    code = (
        "import json, sys\n"
        "from dataclasses import replace\n"
        "from pathlib import Path\n"
        "from rl.baselines import sarl_om as S\n"
        "from sim.env import CrowdNavEnv, SimConfig\n"
        f"sim = replace(SimConfig(), scene={str(sim_cfg.scene)!r}, density=0.0, max_episode_s=5.0, "
        "obs_mode='privileged', action_type='discrete')\n"
        "env = CrowdNavEnv(config=sim)\n"
        f"drv = S.Driver(Path({str(ckpt)!r}))\n"
        "obs, _ = env.reset(seed=123)\n"
        "drv.reset(env, obs)\n"
        "acts = []\n"
        f"for _ in range({len(mine)}):\n"
        "    a = drv.act(env, obs); acts.append(a); obs, *_ = env.step(a)\n"
        "print(json.dumps(acts))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout.strip().splitlines()[-1]) == mine


def test_corrupt_checkpoint_names_the_file(trained, tmp_path):
    import shutil

    ckpt = tmp_path / "sarl_om"
    shutil.copytree(trained[0], ckpt)
    (ckpt / "policy.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(CorruptArtifactError, match="policy.safetensors"):
        S.Driver(ckpt)
