"""DRL-VO's network (package docstring): the early-fusion ResNet features extractor and the SB3 actor-critic around
it."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from rl.baselines.drl_vo.configuration import GOAL_SCALE_M, MAP_CELLS, SPEED_SCALE_MPS
from rl.baselines.drl_vo.observation import kinematic_map, observation_space
from rl.policy import space_to_json


def _norm(c: int) -> nn.GroupNorm:
    return nn.GroupNorm(c // 8, c)


def _conv(cin: int, cout: int, k: int, stride: int = 1, bias: bool = False) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, k, stride, k // 2, bias=bias)


class _Bottleneck(nn.Module):
    """ResNet V1.5 bottleneck (1x1 → 3x3 with the stride → 1x1, expansion 2 as DRL-VO's) with a projected shortcut
    when the shape changes."""

    def __init__(self, cin: int, planes: int, stride: int = 1) -> None:
        super().__init__()
        cout = 2 * planes
        self.branch = nn.Sequential(_conv(cin, planes, 1), _norm(planes), nn.ReLU(),
                                    _conv(planes, planes, 3, stride), _norm(planes), nn.ReLU(),
                                    _conv(planes, cout, 1), _norm(cout))
        self.shortcut = (nn.Sequential(_conv(cin, cout, 1, stride), _norm(cout)) if stride != 1 or cin != cout
                         else nn.Identity())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.branch(x) + self.shortcut(x))


def _block(c: int, mid: int) -> nn.Sequential:
    """DRL-VO's 1x1 → 3x3 → 1x1 residual branch (``conv2_2`` / ``conv3_2``)."""
    return nn.Sequential(_conv(c, mid, 1, bias=True), _norm(mid), nn.ReLU(), _conv(mid, mid, 3, bias=True),
                         _norm(mid), nn.ReLU(), _conv(mid, c, 1, bias=True), _norm(c))


class DRLVOExtractor(BaseFeaturesExtractor):
    """DRL-VO's early-fusion ResNet over [lidar map, kinematic map] (3 x 80 x 80) + the sub-goal → ``features_dim``.

    Shapes with base width w: 3 x 80² → stem (conv s2 + max-pool s2) w x 20² → 2 bottlenecks 2w x 20² → bottleneck
    s2 + block (+ shortcut s2 from the first stage) 4w x 10² → bottleneck s2 + block (+ shortcut s4 from the stem)
    8w x 5² → average pool 8w ⊕ sub-goal 2 → FC ``features_dim`` + ReLU.
    """

    def __init__(self, observation_space: gym.spaces.Dict, width: int = 16, features_dim: int = 256) -> None:
        super().__init__(observation_space, features_dim)
        w = width
        self.range_m = float(np.max(observation_space["scan"].high))
        self.stem = nn.Sequential(_conv(3, w, 3, 2), _norm(w), nn.ReLU(), nn.MaxPool2d(3, 2, 1))
        self.layer1 = nn.Sequential(_Bottleneck(w, w), _Bottleneck(2 * w, w))
        self.layer2 = _Bottleneck(2 * w, 2 * w, 2)
        self.block2, self.short2 = _block(4 * w, 2 * w), nn.Sequential(_conv(2 * w, 4 * w, 1, 2, True), _norm(4 * w))
        self.layer3 = _Bottleneck(4 * w, 4 * w, 2)
        self.block3, self.short3 = _block(8 * w, 4 * w), nn.Sequential(_conv(w, 8 * w, 1, 4, True), _norm(8 * w))
        self.fc = nn.Sequential(nn.Linear(8 * w + 2, features_dim), nn.ReLU())
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.Linear):
                nn.init.xavier_normal_(m.weight)
        for m in self.modules():  # residual branches start as zero (identity blocks), as the original
            if isinstance(m, _Bottleneck):
                nn.init.zeros_(m.branch[-1].weight)

    def maps(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """The network's input image ``B x 3 x 80 x 80``: [lidar map, vx, vy], scaled to about [−1, 1]."""
        scan = 2.0 * obs["scan"] / self.range_m - 1.0  # B x 20 x 80
        scan = scan.unsqueeze(1).repeat(1, 1, MAP_CELLS // scan.shape[1], 1)
        return torch.cat([scan, kinematic_map(obs["peds"]) / SPEED_SCALE_MPS], 1)

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        x = self.stem(self.maps(obs))
        s3 = self.short3(x)
        x = self.layer1(x)
        s2 = self.short2(x)
        x = torch.relu(self.block2(self.layer2(x)) + s2)
        x = torch.relu(self.block3(self.layer3(x)) + s3)
        return self.fc(torch.cat([x.mean((2, 3)), obs["goal"] / GOAL_SCALE_M], 1))


def policy_kwargs(net: dict[str, Any]) -> dict[str, Any]:
    """SB3 ``policy_kwargs`` of the network described by ``net`` (:meth:`Config.net`)."""
    return {"features_extractor_class": DRLVOExtractor,
            "features_extractor_kwargs": {"width": int(net["width"]), "features_dim": int(net["features_dim"])},
            "net_arch": {"pi": [int(n) for n in net["pi"]], "vf": [int(n) for n in net["vf"]]},
            "share_features_extractor": True}


def build_policy(net: dict[str, Any]) -> ActorCriticPolicy:
    """A fresh actor-critic (random weights) over the DRL-VO observation and the normalised (v, ω) box."""
    return ActorCriticPolicy(observation_space(float(net["lidar_range_m"])), gym.spaces.Box(-1.0, 1.0, (2,), np.float32),
                             lambda _: 0.0, **policy_kwargs(net))


def describe_inputs(policy: ActorCriticPolicy) -> dict[str, Any]:
    """A description of the policy's inputs and actions (``policy.json``'s ``observation_space``)."""
    return {**space_to_json(policy.observation_space),
            "actions": "Box([-1, 1]^2): v = (a0 + 1) / 2 · v_max, ω = a1 · ω_max"}
