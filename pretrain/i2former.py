"""I²Former (paper §III-B.2, Eq. 4–8): intention features from 3D human poses, and the robot's interaction with them.

::

    poses  B x K x 17 x 3  (robot frame, m; zeros where a joint was not detected)
    mask   B x K x 17      (True = detected)
    state  B x 5           (s = [g_x, g_y, d_g, v_x, v_y])

    Θ̂ = φ_p(Θ) + joint embedding                          B K 17 d   pose encoder (MLP, ReLU)
    f̂ = LN(MHSA(Θ̂) + Θ̂);  f = AttnPool(LN(FFN(f̂) + f̂))   B K d      IntentFormer (attention over a person's joints)
    e = φ_sp(s)                                            B d        I²-states encoder (MLP, ReLU)
    ẑ = LN(MHCA(e, f) + e);  z = LN(FFN(ẑ) + ẑ)            B d        InteractFormer (robot queries the people)

Masking: undetected joints are keys no query attends to (the paper zero-pads them; a transformer "directs its
attention toward detected keypoints" — we make that exact with a key-padding mask); a person with no detected joint
is absent and masked out of the cross-attention. Two details the paper leaves open, chosen here:

* a learned embedding per joint type is added to φ_p's output, so attention can tell a wrist from a knee (without it
  self-attention over joints is permutation-invariant and only the coordinates identify a joint);
* the cross-attention always sees one extra learned *empty-crowd* key, so a frame with nobody detected has a
  well-defined (finite) z_interact instead of a softmax over nothing.

The output is invariant to the order of the people (attention is permutation-equivariant over keys and the query
is the robot), which the tests check.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from pipeline.core.errors import ConfigError

N_JOINTS = 17
STATE_DIM = 5
POSE_SCALE_M = 5.0  # joint coordinates are divided by this (robot-frame metres → about unit range)
STATE_SCALE = (5.0, 5.0, 10.0, 1.0, 1.0)  # s = [g_x, g_y, d_g, v_x, v_y] divided by these


@dataclass
class I2FormerConfig:
    """Sizes of the I²Former."""

    dim: int = 64  # d: joint, person and robot embedding width
    heads: int = 4  # attention heads (IntentFormer and InteractFormer)
    ffn_mult: int = 2  # FFN hidden width = ffn_mult * dim

    def validate(self) -> None:
        if self.dim < 4 or self.heads < 1 or self.dim % self.heads:
            raise ConfigError(f"i2former: dim must be >= 4 and divisible by heads, got dim={self.dim}, "
                              f"heads={self.heads}")
        if self.ffn_mult < 1:
            raise ConfigError(f"i2former.ffn_mult: expected >= 1, got {self.ffn_mult}")


def mlp(sizes: list[int], last_act: bool = True) -> nn.Sequential:
    """Linear + ReLU layers through ``sizes`` (ReLU after the last one when ``last_act``)."""
    layers: list[nn.Module] = []
    for k, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        layers.append(nn.Linear(a, b))
        if last_act or k < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def attention_kernel(x: torch.Tensor):
    """The scaled-dot-product kernel our attention trains with on ``x``'s device: on the CPU, with gradients, torch's
    plain (math) kernel rather than its flash kernel — over a person's 17 joints and a crowd of <= 11 keys the flash
    kernel's backward under bfloat16 autocast (the students' cloning, ``train.dagger.bc_precision``) is ≈ 3-4x slower
    and took 28 % of a `full` cloning epoch (docs/results.md, Performance); same maths, another summation order.
    Without gradients (feature caches, PPO's rollouts, a driver's decision: :func:`rl.policy.act` and
    :func:`rl.policy.action_logits` run under ``no_grad``) and on other devices torch's own choice stays, faster there
    (0.89 vs 1.02 ms for one frame's I²Former on one thread)."""
    return sdpa_kernel(SDPBackend.MATH) if x.device.type == "cpu" and torch.is_grad_enabled() else nullcontext()


def normalise_state(state: torch.Tensor) -> torch.Tensor:
    """``s`` divided by :data:`STATE_SCALE` (a fixed constant, so no statistic has to travel with a checkpoint)."""
    return state / state.new_tensor(STATE_SCALE)


class AttnPool(nn.Module):
    """Attention pooling over a set: a learned score per element, a masked softmax, the weighted sum."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.score = nn.Linear(dim, 1)

    def forward(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """``... x S x d`` elements, ``... x S`` validity (at least one True per set) → ``... x d``."""
        s = self.score(x).squeeze(-1).masked_fill(~valid, float("-inf"))
        return (torch.softmax(s, -1).unsqueeze(-1) * x).sum(-2)


class IntentFormer(nn.Module):
    """Per person: MHSA over the joints + residual + LN, FFN + residual + LN, attention pooling → ``f_ped``."""

    def __init__(self, dim: int, heads: int, ffn_mult: int) -> None:
        super().__init__()
        self.mhsa = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.ln1 = nn.LayerNorm(dim)
        self.ffn = nn.Sequential(nn.Linear(dim, ffn_mult * dim), nn.ReLU(), nn.Linear(ffn_mult * dim, dim))
        self.ln2 = nn.LayerNorm(dim)
        self.pool = AttnPool(dim)

    def forward(self, joints: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """``P x 17 x d`` joint embeddings, ``P x 17`` detected joints (>= 1 per person) → ``P x d``."""
        with attention_kernel(joints):
            a, _ = self.mhsa(joints, joints, joints, key_padding_mask=~valid, need_weights=False)
        f = self.ln1(a + joints)
        f = self.ln2(self.ffn(f) + f)
        return self.pool(f, valid)


class InteractFormer(nn.Module):
    """The robot embedding queries the people: MHCA + residual + LN, FFN + residual + LN → ``z_interact``."""

    def __init__(self, dim: int, heads: int, ffn_mult: int) -> None:
        super().__init__()
        self.mhca = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.empty = nn.Parameter(torch.zeros(1, 1, dim))  # the always-present empty-crowd key
        self.ln1 = nn.LayerNorm(dim)
        self.ffn = nn.Sequential(nn.Linear(dim, ffn_mult * dim), nn.ReLU(), nn.Linear(ffn_mult * dim, dim))
        self.ln2 = nn.LayerNorm(dim)

    def forward(self, robot: torch.Tensor, people: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """``B x d`` query, ``B x K x d`` people, ``B x K`` present → ``B x d``."""
        b = robot.shape[0]
        keys = torch.cat([self.empty.expand(b, 1, -1), people], 1)
        valid = torch.cat([present.new_ones(b, 1), present], 1)
        q = robot.unsqueeze(1)
        with attention_kernel(q):
            a, _ = self.mhca(q, keys, keys, key_padding_mask=~valid, need_weights=False)
        z = self.ln1(a + q)
        z = self.ln2(self.ffn(z) + z)
        return z.squeeze(1)


class I2Former(nn.Module):
    """Poses + mask + robot state → ``z_interact`` (``B x dim``); see the module docstring."""

    def __init__(self, cfg: I2FormerConfig | None = None) -> None:
        super().__init__()
        cfg = cfg or I2FormerConfig()
        cfg.validate()
        self.cfg = cfg
        d = cfg.dim
        self.pose_encoder = mlp([3, d, d])  # φ_p
        self.joint_embedding = nn.Parameter(torch.randn(N_JOINTS, d) * 0.02)
        self.intent = IntentFormer(d, cfg.heads, cfg.ffn_mult)
        self.state_encoder = mlp([STATE_DIM, d, d])  # φ_sp
        self.interact = InteractFormer(d, cfg.heads, cfg.ffn_mult)

    @property
    def out_dim(self) -> int:
        return self.cfg.dim

    def person_features(self, poses: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``f_ped`` ``B x K x d`` and ``present`` ``B x K`` (a person with at least one detected joint)."""
        b, k = poses.shape[:2]
        valid = mask.bool()
        present = valid.any(-1)
        x = self.pose_encoder(poses / POSE_SCALE_M) + self.joint_embedding
        x = x.flatten(0, 1)  # (B K) x 17 x d
        v = valid.flatten(0, 1)
        f = x.new_zeros(b * k, self.cfg.dim)
        rows = present.flatten()
        if bool(rows.any()):  # only people with a detected joint go through the IntentFormer
            f = f.index_put((rows.nonzero(as_tuple=True)[0],), self.intent(x[rows], v[rows]))
        return f.view(b, k, -1), present

    def forward(self, poses: torch.Tensor, mask: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        f, present = self.person_features(poses.float(), mask)
        e = self.state_encoder(normalise_state(state.float()))  # e_robot
        return self.interact(e, f, present)
