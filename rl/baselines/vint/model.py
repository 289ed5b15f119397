"""The ViNT-style network (package docstring): image encoder, point-goal MLP, transformer decoder, distance and
waypoint heads."""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from rl.baselines.vint.configuration import ENCODERS, IMAGENET_MEAN, IMAGENET_STD


class PositionalEncoding(nn.Module):
    """Sinusoidal positions added to the tokens (ViNT's; buffer ``pos_enc`` ``1 x seq_len x E``)."""

    def __init__(self, dim: int, seq_len: int) -> None:
        super().__init__()
        pos = torch.arange(seq_len, dtype=torch.float32)[:, None]
        div = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
        enc = torch.zeros(seq_len, dim)
        enc[:, 0::2] = torch.sin(pos * div)
        enc[:, 1::2] = torch.cos(pos * div)[:, : dim // 2]
        self.register_buffer("pos_enc", enc[None])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.pos_enc[:, : x.shape[1]]


class Decoder(nn.Module):
    """ViNT's ``MultiLayerDecoder``: positions, a pre-norm transformer encoder over the tokens, then the flattened
    tokens through an MLP (ReLU after every layer). ``B x T x E -> B x output_layers[-1]``."""

    def __init__(self, dim: int, seq_len: int, output_layers: list[int], heads: int, layers: int,
                 ff_factor: int) -> None:
        super().__init__()
        self.positional_encoding = PositionalEncoding(dim, seq_len)
        layer = nn.TransformerEncoderLayer(dim, heads, ff_factor * dim, activation="gelu", batch_first=True,
                                           norm_first=True)
        self.sa_decoder = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        widths = [seq_len * dim, dim, *output_layers]
        self.output_layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:], strict=True))
        # He initialisation (zero biases) of the ReLU MLP: with PyTorch's default Linear initialisation the signal
        # shrinks layer by layer and the biases decide each unit, so most units start on or off for every input
        # and the trained network ignored the goal and never fitted the steering
        # (docs/notes/2026-11-vint-does-not-learn-steering.md)
        for lin in self.output_layers:
            nn.init.kaiming_normal_(lin.weight, nonlinearity="relu")
            nn.init.zeros_(lin.bias)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        x = self.sa_decoder(self.positional_encoding(tokens)).flatten(1)
        for lin in self.output_layers:
            x = F.relu(lin(x))
        return x


def _cnn_encoder() -> tuple[nn.Module, tuple[int, int], int]:
    """The CPU-sized image encoder: (module, pooled grid, channels)."""
    def block(a: int, b: int, k: int, s: int) -> list[nn.Module]:
        return [nn.Conv2d(a, b, k, s, k // 2), nn.SiLU()]

    layers = [*block(3, 32, 5, 2), *block(32, 64, 3, 2), *block(64, 128, 3, 2), *block(128, 128, 3, 1)]
    return nn.Sequential(*layers), (2, 4), 128


def _efficientnet_encoder() -> tuple[nn.Module, tuple[int, int], int]:
    """torchvision's EfficientNet-B0 trunk (random init; the classifier dropped), global pooling as ViNT."""
    # lazily: torchvision takes seconds to import, and only this optional encoder needs it
    from torchvision.models import efficientnet_b0

    return efficientnet_b0(weights=None).features, (1, 1), 1280


class ViNTStyle(nn.Module):
    """ViNT's network with a point goal (package docstring). Inputs: images ``B x (P+1) x 3 x h x 2w`` uint8 (oldest
    first), goal features ``B x 3``; outputs: distance ``B`` (steps) and waypoints ``B x H x 4`` (normalised
    Δx, Δy summed over steps; unit cos, sin)."""

    def __init__(self, encoder: str, image_hw: list[int], context: int, horizon: int, embed_dim: int, layers: int,
                 heads: int, ff_factor: int, output_layers: list[int]) -> None:
        super().__init__()
        if encoder not in ENCODERS:
            raise ValueError(f"unknown encoder {encoder!r} (expected one of {list(ENCODERS)})")
        self.encoder, self.image_hw, self.context, self.horizon = encoder, list(image_hw), context, horizon
        self.embed_dim, self.layers, self.heads, self.ff_factor = embed_dim, layers, heads, ff_factor
        self.output_layers_sizes = list(output_layers)
        trunk, grid, channels = _cnn_encoder() if encoder == "cnn" else _efficientnet_encoder()
        self.obs_encoder = trunk
        self.pool = nn.AdaptiveAvgPool2d(grid)
        self.compress_obs_enc = nn.Linear(channels * grid[0] * grid[1], embed_dim)
        self.goal_mlp = nn.Sequential(nn.Linear(3, 64), nn.ReLU(), nn.Linear(64, embed_dim))
        self.decoder = Decoder(embed_dim, context + 2, list(output_layers), heads, layers, ff_factor)
        self.dist_predictor = nn.Sequential(nn.Linear(output_layers[-1], 1))
        self.action_predictor = nn.Sequential(nn.Linear(output_layers[-1], horizon * 4))
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def is_faithful_size(self) -> bool:
        """True for the released ViNT's sizes (what :func:`load_released_weights` accepts)."""
        return (self.encoder == "efficientnet_b0" and self.embed_dim == 512 and self.context == 5
                and self.horizon == 5 and self.layers == 4 and self.heads == 4 and self.ff_factor == 4
                and self.output_layers_sizes == [256, 128, 64, 32])

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """``N x 3 x h x 2w`` uint8 images -> ``N x E`` tokens."""
        x = (images.float() / 255.0 - self.mean) / self.std
        return self.compress_obs_enc(self.pool(self.obs_encoder(x)).flatten(1))

    def head(self, obs_tokens: torch.Tensor, goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``B x (P+1) x E`` observation tokens and ``B x 3`` goal features -> (distance ``B``, waypoints
        ``B x H x 4``)."""
        tokens = torch.cat([obs_tokens, self.goal_mlp(goal)[:, None]], 1)
        z = self.decoder(tokens)
        raw = self.action_predictor(z).view(-1, self.horizon, 4)
        wp = torch.cat([torch.cumsum(raw[..., :2], 1), F.normalize(raw[..., 2:], dim=-1)], -1)
        return self.dist_predictor(z)[:, 0], wp

    def forward(self, images: torch.Tensor, goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, t = images.shape[:2]
        return self.head(self.encode(images.flatten(0, 1)).view(b, t, -1), goal)


def build_model(net: dict[str, Any]) -> ViNTStyle:
    """The network described by ``policy.json``'s ``net`` (:meth:`Config.net`)."""
    return ViNTStyle(**net)
