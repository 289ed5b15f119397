"""SARL*-OM's value network (package docstring): SARL's attention over the humans plus an angular-map branch."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from rl.baselines.sarl_om.configuration import HUMAN_DIM, KEYS, SELF_DIM


def _mlp(sizes: list[int], last_relu: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    for k in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[k], sizes[k + 1]))
        if k < len(sizes) - 2 or last_relu:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class SarlOMValue(nn.Module):
    """V(joint state): SARL's attention network with an angular-map branch (sizes in the package docstring)."""

    def __init__(self, om_sectors: int, mlp1: tuple[int, ...] = (150, 100), mlp2: tuple[int, ...] = (100, 50),
                 attention: tuple[int, ...] = (100, 100), om: tuple[int, ...] = (64, 32),
                 mlp3: tuple[int, ...] = (150, 100, 100)) -> None:
        super().__init__()
        self.spec = {"om_sectors": om_sectors, "mlp1": list(mlp1), "mlp2": list(mlp2), "attention": list(attention),
                     "om": list(om), "mlp3": list(mlp3)}
        self.mlp1 = _mlp([SELF_DIM + HUMAN_DIM, *mlp1], True)
        self.mlp2 = _mlp([mlp1[-1], *mlp2], False)
        self.attention = _mlp([2 * mlp1[-1], *attention, 1], False)
        self.om = _mlp([om_sectors, *om], True)
        self.mlp3 = _mlp([SELF_DIM + mlp2[-1] + om[-1], *mlp3, 1], False)

    def forward(self, self_state: torch.Tensor, humans: torch.Tensor, mask: torch.Tensor,
                om: torch.Tensor) -> torch.Tensor:
        """``B x 6``, ``B x K x 7``, ``B x K`` (1 = present), ``B x S`` -> ``B`` values."""
        b, k, _ = humans.shape
        m = mask.to(humans.dtype)
        x = torch.cat([self_state[:, None, :].expand(b, k, SELF_DIM), humans], -1)
        e = self.mlp1(x)  # B x K x 100
        glob = (e * m[..., None]).sum(1) / m.sum(1, keepdim=True).clamp(min=1.0)
        scores = self.attention(torch.cat([e, glob[:, None, :].expand_as(e)], -1))[..., 0]
        w = torch.softmax(scores.masked_fill(m <= 0, -1e9), -1) * m  # an empty crowd: all weights 0
        crowd = (w[..., None] * self.mlp2(e)).sum(1)
        return self.mlp3(torch.cat([self_state, crowd, self.om(om)], -1))[:, 0]


def build(net: dict[str, Any]) -> SarlOMValue:
    """The network described by ``policy.json``'s ``net``."""
    return SarlOMValue(int(net["om_sectors"]), tuple(net["mlp1"]), tuple(net["mlp2"]), tuple(net["attention"]),
                       tuple(net["om"]), tuple(net["mlp3"]))


def to_tensors(batch: dict[str, np.ndarray]) -> list[torch.Tensor]:
    """The joint-state arrays (:data:`KEYS` order) as float32 tensors: the network's inputs."""
    return [torch.as_tensor(batch[k], dtype=torch.float32) for k in KEYS]
