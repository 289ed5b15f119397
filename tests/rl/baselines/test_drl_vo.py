"""DRL-VO baseline: its observation, its velocity-obstacle reward, learning a trivial scene, reloading, corruption."""

import json
import math
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from pipeline.core.errors import ConfigError, CorruptArtifactError
from rl.baselines import drl_vo
from rl.baselines.common import save_baseline
from rl.policy import freeze_actor
from rl.stage import TeacherConfig, TrainConfig
from rl.teacher import CurriculumStage
from sim.env import CrowdNavEnv, SimConfig

ROOT = Path(__file__).resolve().parents[3]
# an empty 8 x 8 m room, goals 2.5-3 m away: driving straight ahead reaches few of them (start heading ±0.5 rad off)
EMPTY_ROOM = {"name": "empty_room", "split": "train", "description": "test: an empty 8 x 8 m room",
              "bounds": [0.0, 8.0, 0.0, 8.0], "obstacles": [], "start_goal": {"distance_m": [2.5, 3.0],
                                                                              "clearance_m": 0.5}}
SEEDS = list(range(100, 110))


class _Rows:
    """A ``log`` that keeps its rows."""

    def __init__(self) -> None:
        self.rows: list[tuple[str, int, dict]] = []

    def add(self, phase: str, step: int, **values: float) -> None:
        self.rows.append((phase, step, values))


def _env(scene: str, density: float = 0.0, **over) -> CrowdNavEnv:
    return CrowdNavEnv(config=replace(SimConfig(), scene=scene, density=density, obs_mode="privileged",
                                      action_type="continuous", info_level="basic", **over))


def _drive(ckpt: Path, scene: str, seed: int) -> tuple[str, list[list[float]]]:
    """One seeded episode with the checkpoint's driver: (outcome, actions)."""
    driver = drl_vo.Driver(ckpt)
    env = _env(scene, max_episode_s=8.0)
    obs, _ = env.reset(seed=seed)
    driver.reset(env, obs)
    actions = []
    while True:
        a = driver.act(env, obs, None)
        actions.append([float(x) for x in a])
        obs, _, term, trunc, info = env.step(a)
        if term or trunc:
            return info["outcome"], actions


def _success_rate(ckpt: Path, scene: str) -> float:
    return float(np.mean([_drive(ckpt, scene, s)[0] == "success" for s in SEEDS]))


# ---------------------------------------------------------------------------------------------------- observation
def test_kinematic_map_puts_a_pedestrian_in_its_cell_with_its_robot_frame_velocity():
    """A pedestrian 4.06 m ahead, 1.44 m left of a robot facing +y (world), walking at 1 m/s along +x (world): its
    robot-frame velocity is (0, −1) m/s, in cell (⌊4.06 / 0.125⌋, ⌊(5 − 1.44) / 0.125⌋) = (32, 28); every other
    pedestrian is behind the robot, outside the map."""
    env = _env("open_crowd", 0.1)
    env.reset(seed=0)
    assert env.crowd.n >= 2
    env.robot = np.array([env.robot[0], env.robot[1], math.pi / 2])
    x, y = env.robot[:2]
    forward, left = 4.06, 1.44
    env.crowd.pos[:] = np.stack([x + 0.7 * np.arange(env.crowd.n) - 3.0, np.full(env.crowd.n, y - 2.0)], -1)  # behind
    env.crowd.pos[0] = [x - left, y + forward]  # facing +y: forward = +y world, left = −x world
    env.crowd.vel[:] = 0.5
    env.crowd.vel[0] = [1.0, 0.0]
    observer = drl_vo.Observer(**drl_vo.Config().sensors())
    observer.reset(env)
    o = observer(env)
    assert observer.space.contains({k: v.astype(np.float32) for k, v in o.items()})
    m = drl_vo.kinematic_map(torch.as_tensor(o["peds"])[None])[0].numpy()
    assert m.shape == (2, 80, 80)
    np.testing.assert_allclose(m[:, 32, 28], [0.0, -1.0], atol=1e-5)
    m[:, 32, 28] = 0.0
    assert not m.any(), "cells other than the pedestrian's are set"
    # the lidar history map: 10 identical scans after a reset, min <= mean per bin, within range; the pedestrian's
    # bin (bearing 19.5° left of the heading, 2.25° bins from the right) returns at most its body surface
    s = o["scan"]
    assert s.shape == (20, 80) and (s >= 0).all() and (s <= 30.0).all()
    np.testing.assert_array_equal(s[0::2], np.repeat(s[:1], 10, 0))
    assert (s[0::2] <= s[1::2] + 1e-5).all()
    b = int((math.degrees(math.atan2(left, forward)) + 90.0) // 2.25)
    assert s[-2, b] <= math.hypot(forward, left) - env.crowd.radius[0] + 1e-3
    env.step(env.encode_command(0.0, 0.0))
    s2 = observer(env)["scan"]
    np.testing.assert_array_equal(s2[:-2], s[2:])  # the history shifts by one scan


# --------------------------------------------------------------------------------------------------------- reward
@pytest.mark.parametrize(("ped", "blocked"), [
    ([2.0, 0.0, 0.0, 0.0], True),  # standing on the way to the sub-goal
    ([2.0, 3.0, 0.0, 0.0], False),  # standing off to the side
    ([2.0, 2.0, 0.0, -1.0], True),  # crossing toward the robot's path: relative velocity (1, 1) points at it
    ([2.0, 2.0, 0.0, 1.0], False),  # walking away from the path: relative velocity (1, −1) misses it
    ([8.0, 0.0, 0.0, 0.0], False),  # beyond the 7 m range
])
def test_vo_reward_penalises_heading_into_a_velocity_obstacle(ped, blocked):
    cfg = drl_vo.RewardConfig()
    goal = np.array([2.0, 0.0])  # the sub-goal straight ahead; the robot moves at 1 m/s
    heading = drl_vo.vo_heading(goal, np.array([ped]), 1.0, 0.3, cfg.vo_range_m, cfg.vo_headings)
    r = drl_vo.reward_terms(cfg, None, 3.0, 3.0, 10.0, 0.0, heading, 0.3)
    if blocked:
        assert abs(heading) > 0.3  # the nearest free heading is off the cone
        assert r["heading"] < cfg.angle * (cfg.angle_thresh_rad - 0.3)
    else:
        assert heading == 0.0
        assert r["heading"] == pytest.approx(cfg.angle * cfg.angle_thresh_rad)
    assert r["total"] == pytest.approx(r["heading"])  # no progress, no obstacle, no rotation


def test_reward_terminal_and_shaping_terms():
    cfg = drl_vo.RewardConfig()
    assert drl_vo.reward_terms(cfg, "success", 0.2, 0.3, 10.0, 0.0, 0.0, 0.3)["goal"] == 20.0
    assert drl_vo.reward_terms(cfg, "timeout", 2.0, 2.0, 10.0, 0.0, 0.0, 0.3)["goal"] == -20.0
    assert drl_vo.reward_terms(cfg, "collision_pedestrian", 2.0, 2.0, 0.2, 0.0, 0.0, 0.3)["collision"] == -20.0
    r = drl_vo.reward_terms(cfg, None, 1.9, 2.0, 0.5, 1.5, 0.0, 0.3)
    assert r["goal"] == pytest.approx(0.32) and r["collision"] == pytest.approx(-0.2 * 0.4)
    assert r["rotation"] == pytest.approx(-0.15)
    assert drl_vo.vo_heading(np.array([1.0, 1.0]), np.zeros((0, 5)), 1.0, 0.3, 7.0, 60) == pytest.approx(math.pi / 4)


def test_config_validate_names_the_field():
    with pytest.raises(ConfigError, match="lidar_rays"):
        drl_vo.Config(lidar_rays=100).validate()
    with pytest.raises(ConfigError, match="width"):
        drl_vo.Config(width=12).validate()
    with pytest.raises(ConfigError, match="unknown"):
        drl_vo.Config(ppo={"n_stepz": 3}).validate()
    drl_vo.Config().validate()


def test_freeze_actor_leaves_only_the_value_branch_trainable():
    c = replace(drl_vo.Config(), width=8, features_dim=32, pi=[16], vf=[16])
    policy = drl_vo.build_policy(c.net())
    frozen = freeze_actor(policy)
    trainable = {n for n, p in policy.named_parameters() if p.requires_grad}
    assert trainable and all(n.startswith(("mlp_extractor.value_net.", "value_net.")) for n in trainable)
    assert {n for n, p in policy.named_parameters() if not p.requires_grad} >= {"log_std", "action_net.weight"}
    assert any(n.startswith("features_extractor.") for n, p in policy.named_parameters() if not p.requires_grad)
    assert len(frozen) + len(trainable) == len(list(policy.parameters()))


# ------------------------------------------------------------------------------------------------------- training
@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """DRL-VO trained on the empty room (8 expert episodes + 256 PPO steps) and an untrained checkpoint."""
    tmp = tmp_path_factory.mktemp("drl_vo")
    scene = tmp / "empty_room.yaml"
    scene.write_text(yaml.safe_dump(EMPTY_ROOM))
    sim = replace(SimConfig(), max_episode_s=8.0)
    teacher = TeacherConfig(bc_episodes=8, curriculum=[CurriculumStage(1.0, [str(scene)], [0.0])])
    c = replace(drl_vo.Config(), width=8, features_dim=64, pi=[64], vf=[64], bc_epochs=30, bc_batch=32, bc_lr=1e-3,
                ppo_steps=256, critic_warmup_steps=128, n_envs=2, subprocess=False,
                ppo={"n_steps": 128, "batch_size": 128, "n_epochs": 2, "learning_rate": 5e-5})
    cfg = TrainConfig(variant="drl_vo", sim=sim, teacher=teacher, drl_vo=c, workers=1, threads=1, progress=False)
    torch.manual_seed(0)
    untrained = tmp / "untrained"
    policy = drl_vo.build_policy(c.net())
    save_baseline(untrained, "drl_vo", policy, c.net(), drl_vo.describe_inputs(policy), {}, observer=c.sensors(),
                  robot={"v_max_mps": 1.0, "omega_max_radps": 2.0})
    log = _Rows()
    summary = drl_vo.train(cfg, tmp / "drl_vo", log)
    return {"scene": str(scene), "ckpt": tmp / "drl_vo", "untrained": untrained, "summary": summary, "log": log}


def test_learns_a_trivial_scene(trained):
    """Measured: 0.1-0.2 before (straight ahead at half speed), 1.0 after."""
    before = _success_rate(trained["untrained"], trained["scene"])
    after = _success_rate(trained["ckpt"], trained["scene"])
    assert after >= before + 0.4 and after >= 0.7, (before, after)
    budget = trained["summary"]["budget"]
    assert budget["expert_episodes"] == 8 and budget["ppo_env_steps"] >= 256 and budget["expert_frames"] > 0
    phases = {p for p, _, _ in trained["log"].rows}
    assert "drl_vo_bc" in phases and "drl_vo_ppo" in phases
    assert (trained["ckpt"] / "ppo" / "last.zip").is_file()


_DRIVE_SCRIPT = """
import json, sys
import torch
from dataclasses import replace
from rl.baselines.drl_vo import Driver
from sim.env import CrowdNavEnv, SimConfig
torch.set_num_threads(1)
driver = Driver(sys.argv[1])
env = CrowdNavEnv(config=replace(SimConfig(), scene=sys.argv[2], density=0.0, obs_mode="privileged",
                                 action_type="continuous", info_level="basic", max_episode_s=8.0))
obs, _ = env.reset(seed=int(sys.argv[3]))
driver.reset(env, obs)
actions = []
while True:
    a = driver.act(env, obs, None)
    actions.append([float(x) for x in a])
    obs, _, term, trunc, info = env.step(a)
    if term or trunc:
        break
print(json.dumps([info["outcome"], actions]))
"""


def test_reloads_in_a_fresh_process_and_reproduces_its_actions(trained):
    torch.set_num_threads(1)
    outcome, actions = _drive(trained["ckpt"], trained["scene"], 123)
    res = subprocess.run([sys.executable, "-c", _DRIVE_SCRIPT, str(trained["ckpt"]), trained["scene"], "123"],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    outcome2, actions2 = json.loads(res.stdout.strip().splitlines()[-1])
    assert outcome2 == outcome
    np.testing.assert_allclose(np.array(actions2), np.array(actions), atol=1e-5)


def test_corrupt_checkpoint_names_the_file(trained, tmp_path):
    bad = tmp_path / "drl_vo"
    shutil.copytree(trained["ckpt"], bad, ignore=shutil.ignore_patterns("ppo", "bc"))
    (bad / "policy.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(CorruptArtifactError, match="policy.safetensors"):
        drl_vo.Driver(bad)
