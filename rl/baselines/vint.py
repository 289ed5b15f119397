"""ViNT-style baseline (trained on our data): a visual navigation transformer after ViNT (Shah et al., "ViNT: A
Foundation Model for Visual Navigation", CoRL 2023), trained by imitation on our recorded expert dataset.

The released ViNT weights cannot be downloaded here, so this is ViNT's architecture, losses and controller trained
from scratch on ``DATA_DIR/datasets/<repo_id>`` (``make record``); tables and figures call it
"ViNT-style (trained on our data)".

What it observes in our sim: the two RGB cameras (``obs["rgb_left"]``, ``obs["rgb_right"]``, yawed ±35°), each
resized to ``image_hw`` and laid side by side (left | right, the robot's view from left to right) as one image, and
the goal (or the long-horizon waypoint) as a point in the robot frame. No depth, no map, no pedestrian tracks.

Architecture (ViNT's, sizes for a 2-core CPU; ViNT's in brackets)::

    images  B x (P+1) x 3 x h x 2w  uint8, oldest first, the current frame last     (P = context = 5 past frames)
      -> obs_encoder per image: small CNN, 4 conv layers, 2 x 4 average-pooled grid   [EfficientNet-B0, global pool]
         (``encoder="efficientnet_b0"``: torchvision's EfficientNet-B0, random init, global pool, as ViNT)
      -> compress_obs_enc: Linear -> E                                                 (E = embed_dim 128 [512])
    goal    B x 3  [cos θ, sin θ, tanh(d / goal_scale_m)] of the goal point in the robot frame
      -> goal_mlp: 3 -> 64 -> E                                                         [EfficientNet on obs+goal image]
    tokens  B x (P+2) x E -> + sinusoidal positions -> transformer encoder (pre-norm, GELU, dropout 0.1)
                                                        (layers 4 [4], heads 4 [4], feed-forward 4 E [4 E])
      -> flatten -> MLP (P+2)E -> E -> 256 -> 128 -> 64 -> 32 (ReLU)                    [the same]
      -> dist_predictor 32 -> 1: temporal distance to the goal (steps)
      -> action_predictor 32 -> H x 4: per-step deltas (Δx, Δy) summed into waypoints, (cos, sin) of the yaw
         normalised to unit length                                                      (H = horizon = 5 [5])

Waypoints are in the current robot frame (x forward, y left), divided by ``metres_per_step`` =
``v_max * spacing / fps`` (0.2 m with the defaults), as ViNT divides by its data's metres per step.

Training (ViNT's losses): ``L = alpha * 1e-2 * MSE(distance) + (1 - alpha) * MSE(waypoints)`` with alpha = 0.5,
AdamW with cosine decay. Labels from the dataset: the poses ``observation.odom`` at ``t + k * spacing`` (k = 1..H)
relative to the pose at ``t`` (held at the episode's last pose past its end, ViNT's padding); the context frames
``t - j * spacing`` (j = P..1; the first frame repeated before the episode's start); the goal ``observation.goal``
in the robot frame; the distance = steps of ``spacing`` frames to the episode's end, capped at ``max_dist``.
Frames are preloaded at the reduced resolution (uint8); a batch is a few clips of consecutive targets so that each
frame is encoded once per batch. Train / validation split by episode (:func:`pretrain.data.split_episodes`);
optional left-right mirroring (images flipped and swapped, y, yaw and goal negated).

Controller (ViNT's ``pd_controller``): take predicted waypoint ``waypoint_index`` (ViNT's default 2, the third),
scale it back to metres, and with ``DT = spacing / fps`` (one waypoint step)::

    dx ≈ 0 and dy ≈ 0:  v = 0, ω = atan2(sin, cos) / DT
    dx ≈ 0:             v = 0, ω = sign(dy) π / (2 DT)
    otherwise:          v = dx / DT, ω = atan(dy / dx) / DT

clipped to the robot's limits (v ∈ [0, v_max], ω ∈ [−ω_max, ω_max]).

Deviations from ViNT, and why:

* trained from scratch on our expert dataset (about 100 episodes by default) instead of ViNT's 100 h of
  real-robot data and pretrained weights: no download is possible here; hence "ViNT-style (trained on our data)";
* a point goal (goal / waypoint in the robot frame through an MLP) instead of a goal image: our benchmark gives
  point goals; the distance head is kept (its label: steps to the episode's end);
* the default image encoder is a small CNN with a 2 x 4 pooled grid instead of EfficientNet-B0 with global
  pooling (EfficientNet-B0 is selectable): EfficientNet trains too slowly on two CPU cores, and the grid keeps
  where things are in the wide left | right image;
* E = 128 instead of 512 (CPU budget); the two cameras as one side-by-side image (ViNT has one camera);
* mirror augmentation (ViNT's data is not mirrored): it doubles our small dataset and keeps left/right balanced.

Released weights (:func:`load_released_weights`, ``Config.init_weights``): training starts from a state dict in
the released ``vint.pth`` layout when the model is the faithful-size variant (``encoder="efficientnet_b0"``,
``embed_dim=512``, context 5, horizon 5, 4 layers, 4 heads, feed-forward factor 4, output layers
256-128-64-32). Supported: a plain state dict (``.safetensors``, or a torch file of tensors, optionally under
``"model"`` / ``"state_dict"``). The released ``vint.pth`` pickles the whole module (it needs the authors'
``vint_train`` package to unpickle); convert it once with their code:
``torch.save(torch.load("vint.pth", weights_only=False)["model"].state_dict(), "vint_state.pth")``.
Mapped: ``obs_encoder.*`` (efficientnet_pytorch names, mapped in order onto torchvision's, shapes checked; its
``_fc`` is unused), ``compress_obs_enc``, ``decoder.*`` (positions, transformer, output MLP),
``dist_predictor``, ``action_predictor``. Not used: ``goal_encoder`` / ``compress_goal_enc`` (ViNT's image-goal
encoder; ours is a point-goal MLP, trained from its initialisation). Not identical: efficientnet_pytorch pads
stride-2 convolutions TensorFlow-style ("same", asymmetric), torchvision symmetrically, so the loaded encoder's
features differ slightly from the released model's — fine-tune (train) after loading. Not verified against the
real file (unavailable here); tested with a constructed state dict in that layout.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from rl.baselines.common import load_baseline, save_baseline, to_robot_frame

log = logging.getLogger("icrowdnav")

NAME = "vint"
CAMERAS = ("left", "right")  # side by side in this order: the robot's view from left to right
IMAGENET_MEAN = (0.485, 0.456, 0.406)  # ViNT's image normalisation
IMAGENET_STD = (0.229, 0.224, 0.225)
ENCODERS = ("cnn", "efficientnet_b0")


@dataclass
class Config:
    """Training options of the ViNT-style baseline (``train.vint``); defaults = the default profile's budget."""

    repo_id: str = "icrowdnav/expert"  # the recorded dataset: DATA_DIR/datasets/<repo_id> (`make record`)
    episodes: int = 0  # dataset episodes to use (0 = all)
    encoder: str = "cnn"  # per-image encoder: cnn (CPU-sized) | efficientnet_b0 (torchvision, random init)
    image_hw: list[int] = field(default_factory=lambda: [30, 40])  # per camera (height, width) px after resizing
    context: int = 5  # P past frames besides the current one (ViNT: 5)
    horizon: int = 5  # H predicted waypoints (ViNT: 5)
    spacing: int = 2  # dataset frames between context frames and between waypoints (2 at 10 fps = 0.2 s)
    embed_dim: int = 128  # token size E (ViNT: 512)
    layers: int = 4  # transformer layers (ViNT: 4)
    heads: int = 4  # attention heads (ViNT: 4)
    ff_factor: int = 4  # feed-forward width / E (ViNT: 4)
    output_layers: list[int] = field(default_factory=lambda: [256, 128, 64, 32])  # the MLP after the transformer
    goal_scale_m: float = 3.0  # goal distance feature tanh(d / goal_scale_m)
    max_dist: int = 20  # distance label cap, steps (ViNT: max_dist_cat 20)
    alpha: float = 0.5  # loss = alpha * 1e-2 * distance MSE + (1 - alpha) * waypoint MSE (ViNT: 0.5)
    epochs: int = 12  # passes over the training frames (default dataset: ~47 s each at 1 thread)
    clip_len: int = 16  # consecutive targets per clip (their context frames are encoded once)
    clips_per_batch: int = 8  # batch = clips_per_batch x clip_len targets
    lr: float = 5e-4  # AdamW learning rate, cosine decay (ViNT: 5e-4)
    weight_decay: float = 1e-2
    val_fraction: float = 0.1  # episodes held out for the validation loss
    mirror: bool = True  # left-right mirror augmentation (each batch with probability 0.5)
    waypoint_index: int = 2  # the waypoint the controller follows (ViNT's default: 2)
    init_weights: str = ""  # optional released-ViNT state dict to start from (module docstring)

    def validate(self) -> None:
        """Every option checked at once; raises ConfigError naming the option, expected and actual value."""
        def need(ok: bool, what: str, value: Any) -> None:
            if not ok:
                raise ConfigError(f"train.vint.{what}, got {value!r}")

        need(bool(self.repo_id) and "/" in self.repo_id, "repo_id: expected '<owner>/<name>'", self.repo_id)
        need(self.encoder in ENCODERS, f"encoder: expected one of {list(ENCODERS)}", self.encoder)
        need(len(self.image_hw) == 2 and all(isinstance(v, int) and v >= 8 for v in self.image_hw),
             "image_hw: expected [height, width], integers >= 8", self.image_hw)
        for key in ("episodes", "context"):
            need(getattr(self, key) >= 0, f"{key}: expected an integer >= 0", getattr(self, key))
        for key in ("horizon", "spacing", "layers", "heads", "ff_factor", "max_dist", "epochs", "clip_len",
                    "clips_per_batch"):
            need(getattr(self, key) >= 1, f"{key}: expected an integer >= 1", getattr(self, key))
        need(self.embed_dim >= 1 and self.embed_dim % self.heads == 0,
             f"embed_dim: expected a positive multiple of heads ({self.heads})", self.embed_dim)
        need(len(self.output_layers) >= 1 and all(v >= 1 for v in self.output_layers),
             "output_layers: expected a non-empty list of positive widths", self.output_layers)
        need(0 <= self.waypoint_index < self.horizon, f"waypoint_index: expected 0..{self.horizon - 1}",
             self.waypoint_index)
        need(0.0 <= self.alpha <= 1.0, "alpha: expected a number in [0, 1]", self.alpha)
        need(self.lr > 0 and self.weight_decay >= 0, "lr / weight_decay: expected lr > 0, weight_decay >= 0",
             (self.lr, self.weight_decay))
        need(0.0 < self.val_fraction < 1.0, "val_fraction: expected a number in (0, 1)", self.val_fraction)
        need(self.goal_scale_m > 0, "goal_scale_m: expected > 0", self.goal_scale_m)

    def net(self) -> dict[str, Any]:
        """What :func:`build_model` builds (``policy.json``'s ``net``)."""
        return {"encoder": self.encoder, "image_hw": list(self.image_hw), "context": self.context,
                "horizon": self.horizon, "embed_dim": self.embed_dim, "layers": self.layers, "heads": self.heads,
                "ff_factor": self.ff_factor, "output_layers": list(self.output_layers)}


# ------------------------------------------------------------------------------------------------------- model
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
    from torchvision.models import efficientnet_b0

    return efficientnet_b0(weights=None).features, (1, 1), 1280


class ViNTStyle(nn.Module):
    """ViNT's network with a point goal (module docstring). Inputs: images ``B x (P+1) x 3 x h x 2w`` uint8 (oldest
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


# ------------------------------------------------------------------------------------------------ released weights
_BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
_B0_BLOCKS = 16  # EfficientNet-B0: 1 + 2 + 2 + 3 + 3 + 4 + 1 MBConv blocks


def efficientnet_pytorch_b0_keys() -> list[str]:
    """The ``efficientnet_pytorch`` EfficientNet-B0 state-dict keys (without ``_fc``) in module order — the same
    order as torchvision's ``efficientnet_b0().features`` (stem, 16 MBConv blocks, head)."""
    keys = ["_conv_stem.weight", *(f"_bn0.{b}" for b in _BN)]
    for i in range(_B0_BLOCKS):
        p = f"_blocks.{i}."
        if i > 0:  # block 0 has expand ratio 1: no expansion convolution
            keys += [p + "_expand_conv.weight", *(p + f"_bn0.{b}" for b in _BN)]
        keys += [p + "_depthwise_conv.weight", *(p + f"_bn1.{b}" for b in _BN),
                 *(p + f"_se_{n}.{w}" for n in ("reduce", "expand") for w in ("weight", "bias")),
                 p + "_project_conv.weight", *(p + f"_bn2.{b}" for b in _BN)]
    return keys + ["_conv_head.weight", *(f"_bn1.{b}" for b in _BN)]


def _read_state_dict(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise InputMissingError(f"released ViNT weights {path} do not exist (train.vint.init_weights)")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            sd: Any = load_file(str(path))
        else:
            sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch / safetensors raise many types for foreign or broken files
        raise CorruptArtifactError(
            f"{path}: not a readable state dict ({type(e).__name__}: {str(e)[:200]}); the released vint.pth pickles "
            "the whole module: convert it with the authors' code to a state dict first (see rl.baselines.vint)"
        ) from None
    for key in ("model", "state_dict"):
        if isinstance(sd, dict) and isinstance(sd.get(key), dict):
            sd = sd[key]
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise CorruptArtifactError(f"{path}: expected a dict of tensors (a state dict), got {type(sd).__name__}")
    return {k.removeprefix("module."): v for k, v in sd.items()}


def load_released_weights(model: ViNTStyle, path: Path) -> dict[str, list[str]]:
    """Loads a state dict in the released ViNT layout into the faithful-size ``model`` (module docstring).

    Returns:
        ``{"kept": [...], "ignored": [...]}``: our parameters left at their initialisation (the point-goal MLP)
        and the file's keys not used (the image-goal encoder, the EfficientNet classifier).

    Raises:
        ConfigError: ``model`` is not the faithful-size variant.
        InputMissingError: no file. CorruptArtifactError: unreadable, or keys missing / shapes that do not fit
            (all named, with the file).
    """
    path = Path(path)
    if not model.is_faithful_size():
        raise ConfigError(f"released ViNT weights {path} need the faithful-size variant: train.vint.encoder="
                          "efficientnet_b0, embed_dim=512, context=5, horizon=5, layers=4, heads=4, ff_factor=4, "
                          "output_layers=[256, 128, 64, 32]")
    sd = _read_state_dict(path)
    ours = model.state_dict()
    enc_ours = [k for k in ours if k.startswith("obs_encoder.")]
    source = dict(zip(enc_ours, (f"obs_encoder.{k}" for k in efficientnet_pytorch_b0_keys()), strict=True))
    source |= {k: k for k in ours if not k.startswith(("obs_encoder.", "goal_mlp."))}
    optional = {"decoder.positional_encoding.pos_enc"}  # a constant; ours is the same formula
    new, problems = {}, []
    for k, src in source.items():
        if src not in sd:
            if k not in optional:
                problems.append(f"missing {src}")
            continue
        if tuple(sd[src].shape) != tuple(ours[k].shape):
            problems.append(f"{src}: shape {tuple(sd[src].shape)}, expected {tuple(ours[k].shape)}")
            continue
        new[k] = sd[src].to(ours[k].dtype)
    if problems:
        raise CorruptArtifactError(f"{path} does not fit the released ViNT layout ({len(problems)} problem(s)): "
                                   + "; ".join(problems[:8]) + (" ..." if len(problems) > 8 else ""))
    model.load_state_dict(new, strict=False)
    used = set(source.values())
    return {"kept": [k for k in ours if k.startswith("goal_mlp.")], "ignored": sorted(set(sd) - used)}


# ------------------------------------------------------------------------------------------------- labels / data
def resize_images(rgb: np.ndarray, hw: list[int]) -> np.ndarray:
    """``N x 3 x H x W`` uint8 -> ``N x 3 x h x w`` uint8 by area averaging (the same at training and deployment)."""
    x = torch.from_numpy(np.ascontiguousarray(rgb)).float()
    return F.interpolate(x, size=tuple(hw), mode="area").round_().to(torch.uint8).numpy()


def side_by_side(left: np.ndarray, right: np.ndarray, hw: list[int]) -> np.ndarray:
    """Two ``H x W x 3`` camera images -> one ``3 x h x 2w`` uint8 image (left | right)."""
    both = resize_images(np.stack([left, right]).transpose(0, 3, 1, 2), hw)
    return np.concatenate([both[0], both[1]], -1)


def goal_features(rel_xy: np.ndarray, scale_m: float) -> np.ndarray:
    """Goal points ``... x 2`` in the robot frame -> ``... x 3`` [cos θ, sin θ, tanh(d / scale_m)] float32."""
    rel = np.asarray(rel_xy, np.float64)
    ang, d = np.arctan2(rel[..., 1], rel[..., 0]), np.hypot(rel[..., 0], rel[..., 1])
    return np.stack([np.cos(ang), np.sin(ang), np.tanh(d / scale_m)], -1).astype(np.float32)


def world_to_robot(xy: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World points ``N x 2`` into the frames of poses ``N x 3`` (x forward, y left)."""
    d = xy - pose[:, :2]
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)


def context_indices(targets: np.ndarray, start: np.ndarray, context: int, spacing: int) -> np.ndarray:
    """``T x (P+1)`` frame indices of each target's context, oldest first, the target last; before the episode's
    first frame ``start`` that frame is repeated."""
    offsets = np.arange(context, -1, -1) * spacing
    return np.maximum(targets[:, None] - offsets[None, :], start[:, None])


def trajectory_labels(pose: np.ndarray, goal: np.ndarray, targets: np.ndarray, end: np.ndarray, horizon: int,
                      spacing: int, metres_per_step: float, max_dist: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ViNT's labels of some frames.

    Args:
        pose: ``F x 3`` world poses [x, y, yaw] of every frame. goal: ``F x 2`` world goal of every frame.
        targets: ``T`` frame indices. end: ``T`` one past the last frame of each target's episode.
        horizon, spacing: H waypoints, ``spacing`` frames apart. metres_per_step: the normalisation.
        max_dist: the distance label cap (steps).

    Returns:
        waypoints ``T x H x 4`` float32 [Δx, Δy (normalised, the target's robot frame), cos, sin of the relative
        yaw] of the poses ``t + k * spacing`` (k = 1..H; the last pose of the episode past its end); distance
        ``T`` float32: steps of ``spacing`` frames to the episode's last frame, capped at ``max_dist``; goal
        ``T x 2`` float32: the goal in the target's robot frame (m).
    """
    k = np.arange(1, horizon + 1) * spacing
    fut = np.minimum(targets[:, None] + k[None, :], end[:, None] - 1)  # T x H
    p0 = pose[targets]
    rel = world_to_robot(pose[fut].reshape(-1, 3)[:, :2], np.repeat(p0, horizon, 0)).reshape(-1, horizon, 2)
    dyaw = pose[fut][..., 2] - p0[:, None, 2]
    wp = np.concatenate([rel / metres_per_step, np.stack([np.cos(dyaw), np.sin(dyaw)], -1)], -1)
    dist = np.minimum((end - 1 - targets) / spacing, max_dist)
    return wp.astype(np.float32), dist.astype(np.float32), world_to_robot(goal[targets], p0).astype(np.float32)


@dataclass
class Frames:
    """Every frame of some episodes in memory, concatenated in episode order.

    Attributes:
        images: ``F x 3 x h x 2w`` uint8, left | right side by side, at the training resolution.
        pose: ``F x 3`` float64 world [x, y, yaw] (``observation.odom``).
        goal: ``F x 2`` float64 world goal (``observation.goal``).
        slices: ``[start, end)`` of each episode.
    """

    images: np.ndarray
    pose: np.ndarray
    goal: np.ndarray
    slices: list[tuple[int, int]]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``F`` start and end of each frame's episode."""
        start, end = np.zeros(len(self.pose), np.int64), np.zeros(len(self.pose), np.int64)
        for s, e in self.slices:
            start[s:e], end[s:e] = s, e
        return start, end


class _ResizeSink:
    """A write target for :func:`pretrain.data._decode_video_file`: ``sink[i, cam] = 3 x H x W`` frame, resized
    into camera ``cam``'s half of ``images[i]`` (in chunks of ``chunk`` frames: one resize call each; call
    :meth:`flush` after the last frame)."""

    def __init__(self, images: np.ndarray, hw: list[int], chunk: int = 512) -> None:
        self.images, self.hw, self.chunk = images, hw, chunk
        self.keys: list[tuple[int, int]] = []
        self.pending: list[np.ndarray] = []

    def __setitem__(self, key: tuple[int, int], chw: np.ndarray) -> None:
        self.keys.append(key)
        self.pending.append(chw)
        if len(self.pending) >= self.chunk:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        small = resize_images(np.stack(self.pending), self.hw)
        w = self.hw[1]
        rows, cams = np.array(self.keys).T
        for cam in np.unique(cams):
            sel = cams == cam
            self.images[rows[sel], :, :, cam * w:(cam + 1) * w] = small[sel]
        self.keys, self.pending = [], []


def dataset_root(cfg) -> Path:
    """``DATA_DIR/datasets/<repo_id>`` of the train config ``cfg``."""
    return Path(cfg.data_dir) / "datasets" / cfg.vint.repo_id


def _check_dataset(root: Path) -> dict:
    info_path = root / "meta" / "info.json"
    if not info_path.is_file():
        raise InputMissingError(f"vint: no recorded dataset at {root} (missing meta/info.json); make it with "
                                "`make record`")
    try:
        features = json.loads(info_path.read_text())["features"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise CorruptArtifactError(f"{info_path}: unreadable dataset metadata ({type(e).__name__}: {e})") from None
    need = [f"observation.images.{c}" for c in CAMERAS] + ["observation.odom", "observation.goal"]
    missing = [k for k in need if k not in features]
    if missing:
        raise InputMissingError(f"vint: dataset {root} lacks {', '.join(missing)}; record it with `make record`")
    return features


def load_dataset(root: Path, hw: list[int], episodes: int = 0, progress: bool = True) -> tuple[Frames, float]:
    """The first ``episodes`` episodes (0 = all) of a recorded LeRobot dataset at ``hw`` per camera, and its fps.

    Metadata and parquet columns through stock ``LeRobotDataset``; videos decoded sequentially per file by
    :func:`pretrain.data._decode_video_file`, each frame resized as it arrives.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm import tqdm

    from pretrain.data import _decode_video_file

    root = Path(root)
    _check_dataset(root)
    try:
        side = json.loads((root / "meta" / "icrowdnav.json").read_text())
        ds = LeRobotDataset(side.get("repo_id", f"{root.parent.name}/{root.name}"), root=root, video_backend="pyav")
    except Exception as e:  # lerobot raises many types for broken datasets
        raise CorruptArtifactError(f"dataset {root}: cannot open it ({type(e).__name__}: {e})") from None
    fps = float(ds.meta.fps)
    n_eps = ds.meta.total_episodes if episodes <= 0 else min(episodes, ds.meta.total_episodes)
    meta = ds.meta.episodes
    rows = [(int(meta[e]["dataset_from_index"]), int(meta[e]["dataset_to_index"])) for e in range(n_eps)]
    n = sum(b - a for a, b in rows)
    idx = np.concatenate([np.arange(a, b) for a, b in rows])
    cols = ds.hf_dataset.select_columns(["observation.odom", "observation.goal"]).with_format("numpy")
    pose = np.asarray(cols["observation.odom"], np.float64)[idx]
    goal = np.asarray(cols["observation.goal"], np.float64)[idx]
    starts = np.cumsum([0] + [b - a for a, b in rows])
    frames = Frames(np.zeros((n, 3, hw[0], 2 * hw[1]), np.uint8), pose, goal,
                    [(int(s), int(e)) for s, e in zip(starts[:-1], starts[1:], strict=True)])
    sink = _ResizeSink(frames.images, hw)
    for ci, cam in enumerate(CAMERAS):
        key = f"observation.images.{cam}"
        files: dict[Path, dict[int, tuple[float, float, int]]] = {}
        for e in range(n_eps):
            files.setdefault(root / ds.meta.get_video_file_path(e, key), {})[e] = (
                float(meta[e][f"videos/{key}/from_timestamp"]), float(meta[e][f"videos/{key}/to_timestamp"]),
                int(starts[e]))
        placed = 0
        for path, expected in tqdm(files.items(), desc=f"vint: decode {cam}", unit="file", disable=not progress):
            if not path.is_file():
                raise InputMissingError(f"dataset {root}: video file {path} is missing; re-record with `make record`")
            placed += _decode_video_file(path, expected, fps, sink, ci, key)
            sink.flush()
        if placed != n:
            raise CorruptArtifactError(f"dataset {root}: {key}: decoded {placed} frames of the {n} its episodes list")
    return frames, fps


# ---------------------------------------------------------------------------------------------------- training
@dataclass
class Batch:
    """Tensors of one minibatch: ``frames`` (the unique images), ``window`` (``B x (P+1)`` rows of ``frames``),
    ``goal`` ``B x 3``, ``waypoints`` ``B x H x 4``, ``dist`` ``B``."""

    frames: torch.Tensor
    window: torch.Tensor
    goal: torch.Tensor
    waypoints: torch.Tensor
    dist: torch.Tensor


class Trainer:
    """Minibatches and loss of ViNT-style imitation on :class:`Frames` (see the module docstring).

    Args:
        frames: the data. cfg: the options. metres_per_step: the waypoint normalisation.
    """

    def __init__(self, frames: Frames, cfg: Config, metres_per_step: float) -> None:
        self.frames, self.cfg, self.metres_per_step = frames, cfg, metres_per_step
        self.start, self.end = frames.bounds()

    def clips(self, episodes: list[int], rng: np.random.Generator | None) -> list[np.ndarray]:
        """Targets of ``episodes`` cut into clips of ``clip_len`` consecutive frames (shuffled when ``rng``)."""
        out = [np.arange(s, e)[i:i + self.cfg.clip_len] for s, e in (self.frames.slices[k] for k in episodes)
               for i in range(0, e - s, self.cfg.clip_len)]
        if rng is not None:
            out = [out[i] for i in rng.permutation(len(out))]
        return out

    def batch(self, targets: np.ndarray, mirror: bool) -> Batch:
        c = self.cfg
        ctx = context_indices(targets, self.start[targets], c.context, c.spacing)
        uniq, inv = np.unique(ctx, return_inverse=True)
        wp, dist, goal = trajectory_labels(self.frames.pose, self.frames.goal, targets, self.end[targets],
                                           c.horizon, c.spacing, self.metres_per_step, c.max_dist)
        images = self.frames.images[uniq]
        if mirror:  # flip each camera and swap them; the mirror world has y, yaw and the goal's y negated
            w = images.shape[-1] // 2
            images = np.concatenate([images[..., w:][..., ::-1], images[..., :w][..., ::-1]], -1)
            wp = wp * np.array([1, -1, 1, -1], np.float32)
            goal = goal * np.array([1, -1], np.float32)
        return Batch(torch.from_numpy(np.ascontiguousarray(images)), torch.from_numpy(inv.reshape(ctx.shape)),
                     torch.from_numpy(goal_features(goal, c.goal_scale_m)), torch.from_numpy(wp),
                     torch.from_numpy(dist))

    def loss(self, model: ViNTStyle, b: Batch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(total, waypoint MSE, distance MSE): ViNT's ``alpha * 1e-2 * dist + (1 - alpha) * action``."""
        dist, wp = model.head(model.encode(b.frames)[b.window], b.goal)
        action_loss = F.mse_loss(wp, b.waypoints)
        dist_loss = F.mse_loss(dist, b.dist)
        return self.cfg.alpha * 1e-2 * dist_loss + (1 - self.cfg.alpha) * action_loss, action_loss, dist_loss

    def evaluate(self, model: ViNTStyle, episodes: list[int]) -> dict[str, float]:
        """Mean losses over every frame of ``episodes`` (eval mode, no mirroring)."""
        model.eval()
        sums, n = np.zeros(3), 0
        with torch.no_grad():
            for clip_group in _groups(self.clips(episodes, None), self.cfg.clips_per_batch):
                targets = np.concatenate(clip_group)
                sums += len(targets) * np.array([v.item() for v in self.loss(model, self.batch(targets, False))])
                n += len(targets)
        model.train()
        return dict(zip(("loss", "action_loss", "dist_loss"), (sums / max(n, 1)).tolist(), strict=True))

    def fit(self, model: ViNTStyle, train_eps: list[int], val_eps: list[int], seed: int, log=None,
            progress: bool = False) -> dict[str, Any]:
        """Trains ``model`` for ``cfg.epochs``; logs ``train`` / ``val`` rows through ``log.add`` when given.

        Returns the history (``train_loss`` per epoch, ``val`` losses per epoch), ``steps`` and ``frames_per_s``.
        """
        from tqdm import tqdm

        c = self.cfg
        rng = np.random.default_rng(seed)
        torch.manual_seed(seed)
        per_epoch = math.ceil(len(self.clips(train_eps, None)) / c.clips_per_batch)
        opt = torch.optim.AdamW(model.parameters(), lr=c.lr, weight_decay=c.weight_decay)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, per_epoch * c.epochs))
        hist: dict[str, Any] = {"train_loss": [], "val": []}
        step, seen, t0 = 0, 0, time.perf_counter()
        model.train()
        bar = tqdm(total=per_epoch * c.epochs, desc="vint: train", unit="batch", disable=not progress,
                   dynamic_ncols=True)
        for epoch in range(c.epochs):
            total, count = 0.0, 0
            for clip_group in _groups(self.clips(train_eps, rng), c.clips_per_batch):
                targets = np.concatenate(clip_group)
                loss, a_loss, d_loss = self.loss(model, self.batch(targets, c.mirror and rng.random() < 0.5))
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                sched.step()
                step += 1
                seen += len(targets)
                total += loss.item() * len(targets)
                count += len(targets)
                if log is not None and step % 20 == 0:
                    log.add("train", step, loss=loss.item(), action_loss=a_loss.item(), dist_loss=d_loss.item(),
                            lr=sched.get_last_lr()[0])
                bar.update()
                bar.set_postfix(epoch=epoch, loss=f"{loss.item():.4f}")
            hist["train_loss"].append(total / max(count, 1))
            val = self.evaluate(model, val_eps) if val_eps else {}
            hist["val"].append(val)
            if log is not None:
                log.add("epoch", epoch + 1, train_loss=hist["train_loss"][-1], **{f"val_{k}": v for k, v in val.items()})
        bar.close()
        model.eval()
        wall = time.perf_counter() - t0
        return {**hist, "steps": step, "frames_per_s": round(seen / max(wall, 1e-9), 1), "wall_s": round(wall, 1)}


def _groups(items: list, size: int) -> list[list]:
    return [items[i:i + size] for i in range(0, len(items), size)]


# ------------------------------------------------------------------------------------------------ the contract
def inputs(cfg) -> list[Path]:
    """The dataset's metadata, parquet and video files (and ``init_weights``); a missing dataset ->
    InputMissingError naming it and `make record`."""
    cfg.vint.validate()
    root = dataset_root(cfg)
    _check_dataset(root)
    files = [root / "meta" / "info.json", root / "meta" / "icrowdnav.json", *sorted(root.glob("data/**/*.parquet")),
             *sorted(root.glob("videos/observation.images.*/**/*.mp4"))]
    if cfg.vint.init_weights:
        w = Path(cfg.vint.init_weights)
        if not w.is_file():
            raise InputMissingError(f"train.vint.init_weights: {w} does not exist")
        files.append(w)
    return files


def train(cfg, out: Path, log) -> dict[str, Any]:
    """Imitation of the recorded expert (module docstring); writes ``policy.safetensors`` / ``policy.json``.

    ``out`` receives::

        policy.safetensors, policy.json   the weights; net, deploy (spacing, fps, metres_per_step, waypoint_index,
                                          goal_scale_m, max_dist), produced_by (the budget)
    """
    from pretrain.data import split_episodes

    c: Config = cfg.vint
    c.validate()
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    t0 = time.perf_counter()
    root = dataset_root(cfg)
    frames, fps = load_dataset(root, c.image_hw, c.episodes, cfg.progress)
    log_load_s = time.perf_counter() - t0
    train_eps, val_eps = split_episodes(len(frames.slices), c.val_fraction, cfg.seed)
    metres_per_step = cfg.sim.robot.v_max_mps * c.spacing / fps
    torch.manual_seed(cfg.seed)
    model = build_model(c.net())
    released = load_released_weights(model, Path(c.init_weights)) if c.init_weights else None
    trainer = Trainer(frames, c, metres_per_step)
    hist = trainer.fit(model, train_eps, val_eps, cfg.seed, log, cfg.progress)
    deploy = {"spacing": c.spacing, "fps": fps, "metres_per_step": metres_per_step,
              "waypoint_index": c.waypoint_index, "goal_scale_m": c.goal_scale_m, "max_dist": c.max_dist}
    budget = {"dataset": str(root), "episodes": len(frames.slices), "frames": len(frames.pose),
              "train_episodes": len(train_eps), "val_episodes": len(val_eps), "epochs": c.epochs,
              "steps": hist["steps"], "load_s": round(log_load_s, 1), "train_s": hist["wall_s"],
              "wall_s": round(time.perf_counter() - t0, 1), "frames_per_s": hist["frames_per_s"],
              "init_weights": c.init_weights or None}
    inputs_desc = {"images": f"rgb_left | rgb_right resized to {c.image_hw} each, side by side, uint8",
                   "context": f"{c.context} past frames every {c.spacing} dataset frames + the current one",
                   "goal": "goal or waypoint in the robot frame: cos, sin, tanh(d / goal_scale_m)"}
    save_baseline(out, NAME, model, c.net(), inputs_desc, budget, deploy=deploy, released_weights=released)
    val = hist["val"][-1] if hist["val"] else {}
    return {"budget": budget, "train_loss": hist["train_loss"], "val": val}


# ---------------------------------------------------------------------------------------------------- deployment
def vint_controller(waypoint: np.ndarray, dt_s: float, v_max: float, w_max: float, eps: float = 1e-8
                    ) -> tuple[float, float]:
    """ViNT's ``pd_controller``: one waypoint [dx, dy, cos, sin] (metres, robot frame) -> clipped (v, ω);
    ``dt_s`` = the time of one waypoint step."""
    dx, dy, hx, hy = (float(v) for v in waypoint)
    if abs(dx) < eps and abs(dy) < eps:
        v, w = 0.0, math.atan2(hy, hx) / dt_s
    elif abs(dx) < eps:
        v, w = 0.0, math.copysign(math.pi / (2 * dt_s), dy)
    else:
        v, w = dx / dt_s, math.atan(dy / dx) / dt_s
    return float(np.clip(v, 0.0, v_max)), float(np.clip(w, -w_max, w_max))


class ContextBuffer:
    """The last ``context * spacing + 1`` frames of an episode; :meth:`window` = every ``spacing``-th one, oldest
    first, the newest last. The first frame of an episode fills it (ViNT repeats it likewise)."""

    def __init__(self, context: int, spacing: int) -> None:
        self.context, self.spacing = context, spacing
        self.frames: deque[np.ndarray] = deque(maxlen=context * spacing + 1)

    def reset(self) -> None:
        self.frames.clear()

    def push(self, frame: np.ndarray) -> None:
        if not self.frames:
            self.frames.extend([frame] * self.frames.maxlen)
        else:
            self.frames.append(frame)

    def window(self) -> np.ndarray:
        """``(P+1) x ...`` the context frames and the current one."""
        return np.stack(list(self.frames)[:: self.spacing])


class Driver:
    """The ViNT-style policy in the benchmark harness (:class:`evaluation.methods.Driver`): the two camera images
    of ``obs`` into the context buffer, the goal (or ``waypoint``) in the robot frame, ViNT's controller on the
    predicted waypoint."""

    def __init__(self, ckpt: Path) -> None:
        model, desc = load_baseline(Path(ckpt), NAME, build_model)
        self.model: ViNTStyle = model  # type: ignore[assignment]
        try:
            d = desc["deploy"]
            self.spacing_s = float(d["spacing"]) / float(d["fps"])
            self.metres_per_step = float(d["metres_per_step"])
            self.waypoint_index = int(d["waypoint_index"])
            self.goal_scale_m = float(d["goal_scale_m"])
        except (KeyError, TypeError, ValueError) as e:
            raise CorruptArtifactError(f"{Path(ckpt) / 'policy.json'}: bad deploy block ({e!r})") from None
        self.buffer = ContextBuffer(self.model.context, 1)
        self.last_waypoints: np.ndarray | None = None

    def reset(self, env, obs: dict[str, np.ndarray]) -> None:
        steps = round(self.spacing_s / env.cfg.dt_s)
        if steps < 1 or abs(steps * env.cfg.dt_s - self.spacing_s) > 1e-6:
            raise ConfigError(f"vint: the context spacing {self.spacing_s:g} s is not a whole number of env steps "
                              f"(dt_s = {env.cfg.dt_s:g})")
        self.buffer = ContextBuffer(self.model.context, steps)
        self.last_waypoints = None

    def act(self, env, obs: dict[str, np.ndarray], waypoint: np.ndarray | None = None):
        self.buffer.push(side_by_side(obs["rgb_left"], obs["rgb_right"], self.model.image_hw))
        target = env.goal if waypoint is None else waypoint
        goal = goal_features(to_robot_frame(env, np.asarray(target, float)), self.goal_scale_m)
        with torch.no_grad():
            _, wp = self.model(torch.from_numpy(self.buffer.window())[None], torch.from_numpy(goal)[None])
        wp = wp[0].numpy().astype(np.float64)
        wp[:, :2] *= self.metres_per_step
        self.last_waypoints = wp
        r = env.cfg.robot
        v, w = vint_controller(wp[self.waypoint_index], self.spacing_s, r.v_max_mps, r.omega_max_radps)
        return env.encode_command(v, w)

    def bev_panel(self) -> np.ndarray | None:
        return None
