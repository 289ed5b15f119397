"""Saved policies as episode drivers: the MLP head's obstacle shield at evaluation (rl.driver.PolicyDriver)."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from rl.driver import PolicyDriver
from rl.lookahead import ObstacleShield
from rl.policy import action_logits
from sim.env import CrowdNavEnv
from tests.rl.helpers_mlp import N_ROT, SIM, TARGET, save_mlp_student


@pytest.fixture(scope="module")
def episode():
    env = CrowdNavEnv(config=SIM)
    obs, info = env.reset(seed=0)
    yield env, obs, info
    env.close()


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
