"""The ViNT-style baseline's training options (``TrainConfig.vint``) and constants."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from pipeline.core.errors import ConfigError

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
    init_weights: str = ""  # optional released-ViNT state dict to start from (package docstring)

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
