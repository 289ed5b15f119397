"""Loading a state dict in the released ViNT layout into the faithful-size ViNT-style network (package docstring)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from pretrain.checkpoint import read_weights
from rl.baselines.vint.model import ViNTStyle

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
    # unreadable / damaged / non-finite -> one error naming the file
    sd: Any = read_weights(path, hint="the released vint.pth pickles the whole module: convert it with the authors' "
                                      "code to a state dict first (see rl.baselines.vint)")
    for key in ("model", "state_dict"):
        if isinstance(sd, dict) and isinstance(sd.get(key), dict):
            sd = sd[key]
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise CorruptArtifactError(f"{path}: expected a dict of tensors (a state dict), got {type(sd).__name__}")
    return {k.removeprefix("module."): v for k, v in sd.items()}


def load_released_weights(model: ViNTStyle, path: Path) -> dict[str, list[str]]:
    """Loads a state dict in the released ViNT layout into the faithful-size ``model`` (package docstring).

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
