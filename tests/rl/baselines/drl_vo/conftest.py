"""The DRL-VO checkpoints the training and driver tests share (trained once per package)."""

from dataclasses import replace

import pytest
import torch
import yaml

from rl.baselines import drl_vo
from rl.baselines.common import save_baseline
from rl.stage import TeacherConfig, TrainConfig
from rl.teacher import CurriculumStage
from sim.env import SimConfig
from tests.rl.baselines.drl_vo.helpers import EMPTY_ROOM, Rows


@pytest.fixture(scope="package")
def trained(tmp_path_factory):
    """DRL-VO trained on the empty room (8 expert episodes + 256 PPO steps) and an untrained checkpoint."""
    tmp = tmp_path_factory.mktemp("drl_vo")
    scene = tmp / "empty_room.yaml"
    scene.write_text(yaml.safe_dump(EMPTY_ROOM))
    sim = replace(SimConfig(), max_episode_s=8.0)
    teacher = TeacherConfig(bc_episodes=8, curriculum=[CurriculumStage(1.0, [str(scene)], [0.0])])
    c = replace(drl_vo.Config(), width=8, features_dim=64, pi=[64], vf=[64], bc_epochs=30, bc_batch=32, bc_lr=1e-3,
                ppo_steps=256, critic_warmup_steps=128, n_envs=2, subprocess=False, curve_steps=[128],
                ppo={"n_steps": 128, "batch_size": 128, "n_epochs": 2, "learning_rate": 5e-5})
    cfg = TrainConfig(variant="drl_vo", sim=sim, teacher=teacher, drl_vo=c, workers=1, threads=1, progress=False)
    torch.manual_seed(0)
    untrained = tmp / "untrained"
    policy = drl_vo.build_policy(c.net())
    save_baseline(untrained, "drl_vo", policy, c.net(), drl_vo.describe_inputs(policy), {}, observer=c.sensors(),
                  robot={"v_max_mps": 1.0, "omega_max_radps": 2.0})
    log = Rows()
    summary = drl_vo.train(cfg, tmp / "drl_vo", log)
    return {"scene": str(scene), "ckpt": tmp / "drl_vo", "untrained": untrained, "summary": summary, "log": log,
            "cfg": cfg}
