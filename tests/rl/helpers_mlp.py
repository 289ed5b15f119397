"""A student with the paper's MLP head, saved as ``train`` saves it, and the small env its tests drive it in
(test_driver, test_dagger)."""

import torch

from rl.observe import observer_for
from rl.policy import build_policy, describe, save_policy
from sim.env import CameraConfig, SimConfig

SIM = SimConfig(max_episode_s=4.0, camera=CameraConfig(width_px=64, height_px=48), scene="hallway",
                obs_mode="visual", action_type="discrete")
N_ROT = 21
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
