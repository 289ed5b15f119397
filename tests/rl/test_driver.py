"""Saved policies as episode drivers: the MLP head's obstacle shield at evaluation (rl.driver.PolicyDriver)."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from rl.driver import PolicyDriver
from rl.lookahead import ObstacleShield
from rl.observe import observer_for
from rl.policy import action_logits, build_policy, describe, save_policy
from sim.env import CameraConfig, CrowdNavEnv, SimConfig

SIM = SimConfig(max_episode_s=4.0, camera=CameraConfig(width_px=64, height_px=48), scene="hallway",
                obs_mode="visual", action_type="discrete")
N_ROT = 21


@pytest.fixture(scope="module")
def episode():
    env = CrowdNavEnv(config=SIM)
    obs, info = env.reset(seed=0)
    yield env, obs, info
    env.close()


TARGET = 4 * N_ROT + N_ROT // 2  # the fastest straight command


def save_mlp_student(out, info, straight_bias=0.0):
    """A ``no_bev`` student with the paper's MLP head (random weights, plus ``straight_bias`` nats on the fastest
    straight command; no encoder needed), saved as train saves it."""
    space = observer_for(info["cameras"], info["config"], "no_bev", None, "mlp").observation_space
    torch.manual_seed(0)
    net = {"head": "mlp"}
    policy = build_policy("student", "no_bev", space, net)
    with torch.no_grad():
        policy.action_net.bias[TARGET] += straight_bias
    save_policy(out, policy, describe("student", "no_bev", space, net, encoder=None, intention=None))
    return out


@pytest.fixture(scope="module")
def mlp_student(tmp_path_factory, episode):
    return save_mlp_student(tmp_path_factory.mktemp("policy") / "no_bev", episode[2])


def test_mlp_student_with_the_shield_never_picks_an_arc_into_the_scan(tmp_path, mlp_student, episode):
    """``PolicyDriver(ckpt, shield_s)`` on an MLP-head student: off as saved (its observation has no scan); with a
    horizon its observer also perceives the depth scan and each action is the argmax of the head's logits minus
    :class:`rl.lookahead.ObstacleShield`'s penalty — so with a wall all round at 0.6 m it picks no arc that
    intrudes, where the unshielded head does (the same weights)."""
    env, obs, info = episode
    plain, shielded = PolicyDriver(mlp_student), PolicyDriver(mlp_student, shield_s=0.6)
    for d in (plain, shielded):
        d.reset(obs, info)
        d.act(obs, info)
    assert plain.shield is None and "scan" not in plain.last_obs
    assert shielded.shield is not None and shielded.last_obs["scan"].shape == (SIM.scan_rays,)
    # the real scan of the first frame: the action is the shielded argmax
    o = shielded.last_obs
    pen = shielded.shield(torch.as_tensor(o["scan"])[None])[0].numpy()
    assert shielded.act(obs, info) == int(np.argmax(action_logits(shielded.policy, o) - pen))
    # a wall all round at 0.6 m: every fast arc intrudes, the turns on the spot do not
    wall = {**o, "scan": np.full(SIM.scan_rays, 0.6, np.float32)}
    pen = ObstacleShield(SIM.robot, SIM.dt_s, SIM.scan_rays, SIM.scan_range_m, 0.6)(
        torch.as_tensor(wall["scan"])[None])[0].numpy()
    intruding = set(np.flatnonzero(pen > 0).tolist())
    assert intruding and not intruding & set(range(N_ROT))
    # weights whose argmax drives straight into it: the unshielded head picks it, the shielded one does not
    straight = save_mlp_student(tmp_path / "straight", info, straight_bias=100.0)
    plain, shielded = PolicyDriver(straight), PolicyDriver(straight, shield_s=0.6)
    for d in (plain, shielded):
        d.reset(obs, info)
        d.observer = lambda _obs: dict(wall)
    assert TARGET in intruding and plain.act(obs, info) == TARGET
    a = shielded.act(obs, info)
    assert a not in intruding and a == int(np.argmax(action_logits(shielded.policy, wall) - pen))


def test_a_shielded_mlp_student_drives_an_episode(mlp_student):
    """The shielded driver acts through a real episode (the scan perceived each step) on the same weights."""
    env = CrowdNavEnv(config=replace(SIM, max_episode_s=1.0))
    obs, info = env.reset(seed=1)
    d = PolicyDriver(mlp_student, shield_s=0.6)
    d.reset(obs, {**info, "episode_seed": 1})
    steps, done = 0, False
    while not done:
        obs, _, term, trunc, info = env.step(d.act(obs, info))
        steps, done = steps + 1, term or trunc
    env.close()
    assert steps > 0 and d.last_obs["scan"].shape == (SIM.scan_rays,)
