"""Loading a state dict in the released ViNT layout (constructed: the real file cannot be downloaded here)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from pipeline.core.errors import ConfigError, CorruptArtifactError
from rl.baselines.vint import Config, build_model, efficientnet_pytorch_b0_keys, load_released_weights
from tests.rl.baselines.vint.helpers import TINY_NET

FAITHFUL = {"encoder": "efficientnet_b0", "image_hw": [64, 85], "context": 5, "horizon": 5, "embed_dim": 512,
            "layers": 4, "heads": 4, "ff_factor": 4, "output_layers": [256, 128, 64, 32]}


def _released_layout(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """A state dict as the released ViNT names it: efficientnet_pytorch encoder keys, its classifier and an
    image-goal encoder we do not use."""
    sd = model.state_dict()
    enc = [k for k in sd if k.startswith("obs_encoder.")]
    out = {f"obs_encoder.{n}": sd[k] for k, n in zip(enc, efficientnet_pytorch_b0_keys(), strict=True)}
    out |= {k: v for k, v in sd.items() if not k.startswith(("obs_encoder.", "goal_mlp."))}
    out["obs_encoder._fc.weight"] = torch.zeros(1000, 1280)
    out["goal_encoder._conv_stem.weight"] = torch.zeros(32, 6, 3, 3)
    return out


def test_released_layout_loads_and_misfits_are_named(tmp_path: Path) -> None:
    torch.manual_seed(0)
    src = build_model(FAITHFUL)
    path = tmp_path / "vint_state.pth"
    torch.save({"model": _released_layout(src)}, path)
    torch.manual_seed(1)
    dst = build_model(FAITHFUL)
    report = load_released_weights(dst, path)
    assert "goal_encoder._conv_stem.weight" in report["ignored"] and "obs_encoder._fc.weight" in report["ignored"]
    assert report["kept"] and all(k.startswith("goal_mlp.") for k in report["kept"])
    for (k, a), b in zip(src.state_dict().items(), dst.state_dict().values(), strict=True):
        assert torch.equal(a, b) != k.startswith("goal_mlp."), k
    broken = _released_layout(src)
    broken["decoder.output_layers.0.weight"] = torch.zeros(512, 100)
    del broken["dist_predictor.0.bias"]
    torch.save(broken, path)
    with pytest.raises(CorruptArtifactError, match=r"vint_state\.pth.*dist_predictor\.0\.bias") as e:
        load_released_weights(dst, path)
    assert "decoder.output_layers.0.weight" in str(e.value)
    path.write_bytes(b"garbage")
    with pytest.raises(CorruptArtifactError, match="vint_state.pth"):
        load_released_weights(dst, path)
    with pytest.raises(ConfigError, match="faithful-size"):
        load_released_weights(build_model(Config(**TINY_NET).net()), path)
