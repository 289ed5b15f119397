"""rl.policy: what a saved policy refers to, and how it travels (checkpoint bundles for Ray nodes)."""

from __future__ import annotations

import json
import shutil

import pytest
import torch
from safetensors.torch import save_file

from rl.policy import check_checkpoint_weights, checkpoint_bundle, read_policy_json


def test_a_checkpoint_bundle_holds_what_the_policy_acts_with_and_finds_it_where_unpacked(tmp_path, monkeypatch):
    """``eval --ray_files transfer`` ships each method's checkpoint as a bundle: the policy's own files and those of
    its encoder and intention model (not the teacher it was distilled from, not its DAgger subfolders); a policy.json
    written with absolute references (older checkpoints) is bundled with relative ones, so the unpacked copy —
    the data dir gone — reads, verifies and points inside itself."""
    ck = tmp_path / "data" / "checkpoints"
    for d, name in (("bev", "encoder.safetensors"), ("intention", "forecaster.safetensors"),
                    ("policy/teacher", "policy.safetensors"), ("policy/full", "policy.safetensors")):
        (ck / d).mkdir(parents=True)
        save_file({"w": torch.ones(3)}, str(ck / d / name))
    (ck / "policy" / "full" / "dagger" / "iter_0").mkdir(parents=True)
    (ck / "policy" / "full" / "dagger" / "iter_0" / "big.npz").write_bytes(b"x" * 1000)
    ckpt = ck / "policy" / "full"
    (ckpt / "policy.json").write_text(json.dumps({"kind": "student", "variant": "full", "observation_space": {},
                                                  "net": {}, "encoder": str(ck / "bev"),
                                                  "intention": str(ck / "intention"),
                                                  "teacher": str(ck / "policy" / "teacher")}))
    bundle = checkpoint_bundle([ckpt, ckpt])
    assert bundle.root == str(ck) and [n for n, _ in bundle.files] == [
        "bev/encoder.safetensors", "intention/forecaster.safetensors", "policy/full/policy.json",
        "policy/full/policy.safetensors"]
    stored = json.loads(dict(bundle.files)["policy/full/policy.json"])
    assert (stored["encoder"], stored["intention"]) == ("../../bev", "../../intention")
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path / "node"))
    (tmp_path / "node").mkdir()
    shutil.rmtree(tmp_path / "data")
    local = bundle.local(bundle.unpack(), ckpt)
    desc = read_policy_json(local)
    assert desc["encoder"] == str(local.parent.parent / "bev") and desc["intention"] == str(local.parent.parent /
                                                                                            "intention")
    check_checkpoint_weights(local)


def test_a_detached_critic_sends_no_gradient_into_the_shared_extractor():
    """``train.finetune.critic_features: detached`` (rl.policy.detach_critic): the same values, but the value loss
    reaches only the critic's own layers; the policy gradient still trains the shared extractor."""
    from rl.policy import build_policy, detach_critic, obs_to_tensor
    from rl.teacher import SceneMixEnv
    from sim.env import CameraConfig, SimConfig

    env = SceneMixEnv(SimConfig(max_episode_s=4.0, camera=CameraConfig(width_px=64, height_px=48)), [("hallway", 0.1)])
    obs, _ = env.reset(seed=0)
    env.close()
    grads, values = {}, {}
    for mode in ("shared", "detached"):
        torch.manual_seed(0)
        policy = build_policy("teacher", None, env.observation_space, {"encoder": "set"})
        if mode == "detached":
            detach_critic(policy)
            detach_critic(policy)  # idempotent: one hook
        value, log_prob, _ = policy.evaluate_actions(obs_to_tensor(obs), torch.tensor([3]))
        values[mode] = value.detach()
        value.sum().backward(retain_graph=True)
        ext = [p.grad for p in policy.features_extractor.parameters()]
        grads[mode] = (any(g is not None and g.abs().sum() > 0 for g in ext),
                       all(p.grad is not None for p in policy.value_net.parameters()))
        policy.zero_grad()
        log_prob.sum().backward()
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in policy.features_extractor.parameters())
    assert torch.equal(values["shared"], values["detached"])
    assert grads == {"shared": (True, True), "detached": (False, True)}


def test_a_sampling_temperature_sharpens_the_distribution_but_keeps_the_argmax():
    """``train.finetune.sampling_temperature`` (rl.policy.set_sampling_temperature): the distribution PPO samples
    and scores is softmax(logits / T), the most likely action and the weights unchanged; set again, it replaces the
    hook; 1 removes it; a bad value is refused."""
    from rl.policy import build_policy, obs_to_tensor, set_sampling_temperature
    from rl.teacher import SceneMixEnv
    from sim.env import CameraConfig, SimConfig

    env = SceneMixEnv(SimConfig(max_episode_s=4.0, camera=CameraConfig(width_px=64, height_px=48)), [("hallway", 0.1)])
    obs, _ = env.reset(seed=0)
    env.close()
    torch.manual_seed(0)
    policy = build_policy("teacher", None, env.observation_space, {"encoder": "set"}).eval()
    x = obs_to_tensor(obs)
    weights = {k: v.clone() for k, v in policy.state_dict().items()}
    with torch.no_grad():
        base = policy.get_distribution(x).distribution.logits
        for t in (0.5, 0.25):
            set_sampling_temperature(policy, t)
            dist = policy.get_distribution(x).distribution
            assert torch.allclose(dist.logits, torch.log_softmax(base / t, -1), atol=1e-5)
            assert len(policy.action_net._forward_hooks) == 1  # replaced, not stacked
            _, log_prob, entropy = policy.evaluate_actions(x, torch.tensor([3]))  # what PPO's update scores
            assert torch.allclose(log_prob, torch.log_softmax(base / t, -1)[:, 3], atol=1e-5)
            assert float(entropy) < float(torch.distributions.Categorical(logits=base).entropy())
            assert int(dist.logits.argmax()) == int(base.argmax())
        set_sampling_temperature(policy, 1.0)
        assert not policy.action_net._forward_hooks
        assert torch.allclose(policy.get_distribution(x).distribution.logits, torch.log_softmax(base, -1), atol=1e-6)
    assert all(torch.equal(v, weights[k]) for k, v in policy.state_dict().items())
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="sampling temperature: expected a finite number > 0"):
            set_sampling_temperature(policy, bad)
