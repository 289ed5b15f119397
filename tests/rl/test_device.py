"""``train.device``: the named error without CUDA (any machine), and on a CUDA machine the cloning updates, SB3 PPO,
the students' frozen encoder and the spawned DAgger workers, with everything saved loading on the CPU."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.core.config import load_config
from pipeline.core.errors import ConfigError
from rl.stage import TrainConfig

TINY = dict(max_episode_s=3.0)
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def test_train_device_cuda_without_cuda_is_named(monkeypatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ConfigError, match=r"^train\.device: expected a device this machine has .*got 'cuda': CUDA is "
                                          r"not available on this machine"):
        load_config(TrainConfig, "train", "smoke", overrides={"device": "cuda"})
    assert load_config(TrainConfig, "train", "smoke", overrides={"device": "cpu"}).device == "cpu"


def _sim():
    from sim.env import CameraConfig, SimConfig

    return SimConfig(camera=CameraConfig(width_px=64, height_px=48), **TINY)


def _teacher(out: Path, space, net):
    """A random lookahead teacher saved as a finished checkpoint (labels DAgger frames; not a good driver)."""
    from rl.policy import build_policy, describe, save_policy

    torch.manual_seed(0)
    policy = build_policy("teacher", None, space, net)
    save_policy(out, policy, describe("teacher", None, space, net))
    (out / "manifest.json").write_text("{}")
    return policy


@needs_cuda
def test_cloning_and_ppo_on_cuda_save_policies_that_load_on_cpu(tmp_path: Path) -> None:
    from stable_baselines3 import PPO

    from rl.policy import build_policy, describe, load_policy, policy_class, policy_kwargs, save_policy
    from rl.teacher import (
        SceneMixEnv,
        attach_lookahead_cache,
        bc_loss,
        behaviour_clone,
        collect_expert,
        fit_lookahead_linear,
        lookahead_feature_cache,
        make_vec_env,
        policy_logits_values,
        teacher_net,
    )

    sim = _sim()
    data = collect_expert(sim, [("hallway", 0.1)], 2, 0, 0.99, 1, progress=False)
    space = SceneMixEnv(sim, [("hallway", 0.1)]).observation_space
    net = teacher_net({"encoder": "lookahead"}, sim)
    torch.manual_seed(0)
    policy = build_policy("teacher", None, space, net).to("cuda")
    cache = lookahead_feature_cache(policy, data, True)
    fit = fit_lookahead_linear(policy, data, 0.1, mirror=True, cache=cache)
    assert fit["ce_after"] < fit["ce_before"]
    before = bc_loss(policy, data, soft_tau=0.1)
    rows = behaviour_clone(policy, data, 3, 64, 1e-3, 0, progress=False, soft_tau=0.1, mirror=True,
                           frozen=("features_extractor.lookahead.linear.",), cache=cache)
    assert policy.device.type == "cuda" and np.isfinite(rows[-1]["bc_loss"])
    assert bc_loss(policy, data, soft_tau=0.1) < before

    save_policy(tmp_path / "p", policy, describe("teacher", None, space, net))
    loaded, _ = load_policy(tmp_path / "p")
    assert loaded.device.type == "cpu"
    obs = {k: torch.as_tensor(data[k][:16], dtype=torch.float32) for k in space.spaces}
    with torch.no_grad():
        ref, _ = policy_logits_values(policy, {k: v.cuda() for k, v in obs.items()})
        got, _ = policy_logits_values(loaded, obs)
    torch.testing.assert_close(got, ref.cpu(), rtol=1e-3, atol=1e-3)

    venv = make_vec_env(sim, [("hallway", 0.1)], 2, 0, subprocess=False)
    model = PPO(policy_class("teacher", net), venv, policy_kwargs=policy_kwargs("teacher", None, net), seed=0,
                device="cuda", n_steps=32, batch_size=32, n_epochs=1)
    model.policy.load_state_dict(policy.state_dict())
    attach_lookahead_cache(model)
    model.learn(64)
    model.save(tmp_path / "ppo.zip")
    venv.close()
    again = PPO.load(tmp_path / "ppo.zip", device="cpu")
    assert again.policy.device.type == "cpu" and again.num_timesteps == model.num_timesteps


@needs_cuda
def test_student_encoder_on_cuda_matches_cpu_and_dagger_workers_spawn(tmp_path: Path) -> None:
    """The frozen encoder gives the same s_bev on CUDA as on the CPU (mirror stream too); DAgger rollouts with
    ``device: cuda`` run in spawned workers that each load the encoder on the GPU."""
    from pretrain.checkpoint import write_encoder_checkpoint
    from pretrain.model import BEVEncoder, EncoderConfig, PretextHeads
    from rl.dagger import load_features, run_iteration
    from rl.observe import StudentObserver, env_cameras, load_student_encoder
    from rl.teacher import teacher_net
    from sim.env import CrowdNavEnv

    sim = _sim()
    env = CrowdNavEnv(config=replace(sim, scene="hallway", density=0.2, obs_mode="visual"))
    obs, _ = env.reset(seed=3)
    cams = env_cameras(env)
    torch.manual_seed(0)
    enc = BEVEncoder(EncoderConfig(bev_channels=8), cams).eval()
    ckpt = tmp_path / "bev"
    ckpt.mkdir()
    write_encoder_checkpoint(ckpt, enc, PretextHeads(8), {})
    (ckpt / "manifest.json").write_text("{}")
    outs = {}
    for dev in ("cpu", "cuda"):
        observer = StudentObserver("full", cams, load_student_encoder("full", ckpt, dev), sim.detector.max_people,
                                   mirror=True)
        o = obs
        for _ in range(3):  # history: the stream's cache lives on the device
            s = observer(o)
            o, *_ = env.step(np.array([0.5, 0.1], np.float32))
        outs[dev] = s
    env.close()
    for key in ("bev", "bev_mirror"):
        assert isinstance(outs["cuda"][key], np.ndarray)
        np.testing.assert_allclose(outs["cuda"][key], outs["cpu"][key], rtol=1e-2, atol=1e-2)

    penv = CrowdNavEnv(config=replace(sim, scene="hallway", obs_mode="privileged", action_type="discrete"))
    teacher = tmp_path / "teacher"
    _teacher(teacher, penv.observation_space, teacher_net({"encoder": "lookahead"}, sim))
    it = tmp_path / "iter_0"
    jobs = [{"sim": sim, "scene": "hallway", "density": 0.1, "seed": s, "variant": "full", "encoder": str(ckpt),
             "teacher": str(teacher), "student": None, "beta": 1.0, "iteration": 0, "iter_dir": str(it),
             "mirror": True, "head": "mlp", "device": "cuda"} for s in (1, 2)]
    rows = run_iteration(it, jobs, workers=2, progress=False)
    assert len(rows) == 2
    data = load_features([it])
    assert data["bev"].shape[1:] == (8, *(n // 2 for n in enc.grid.shape)) and np.isfinite(data["bev"]).all()
    assert len(data["bev_mirror"]) == len(data["action"]) == sum(r["frames"] for r in rows)
