"""The spatio-temporal BEV encoder (paper §III-B.1), its streaming form and the pretext heads.

Shapes (B batch, T history frames, N cameras, C BEV channels, X x Y BEV cells, H x W images, h x w lift pixels):

* ``rgb``: ``B x T x N x 3 x H x W`` uint8 (or float in [0, 1]);
* ``depth``: ``B x T x N x H x W`` float32 z-depth in m (0 = invalid), full resolution;
* ``poses``: ``B x T x 3`` robot poses ``[x, y, yaw]`` in the world frame (any fixed frame works: only relative
  poses are used);
* ``s_bev``: ``B x C x X x Y`` in the base frame of the newest frame (layout in :mod:`pretrain.geometry`).

Pipeline per frame: ResNet-18 trunk (torchvision architecture; the first ``resnet_stages`` stages) → 1x1 neck to C
channels → bilinear resize to the lift pixels → measured-depth lift + vertical sum pooling (:func:`lift_splat`)
(+ with ``evidence``, a 1x1 projection of the depth's geometric evidence per cell — points in the height band, floor
hits, rays that crossed the cell: :func:`lift_evidence`) → ``x_bev``. Over the window: every past ``x_bev`` is
warped into the newest frame by ego-motion (:func:`warp_bev`), the T maps are stacked in time and a FIERY-style
temporal model (causal 3D convolutions with kernel ``2 x 3 x 3``, T−1 of them, plus a 2D skip from the newest map)
fuses them; with ``decoder: unet`` a BEV encoder-decoder (:class:`BEVDecoder`, three stride-2 stages, receptive
field ≈ 5 m) follows, residual to its input; the result is ``s_bev``. With ``fuse_pool: p > 1`` the warp, the
temporal model and the decoder run on the ``p x p`` average-pooled maps (``p²`` fewer cells: the dearest part of a
streaming step, ~70 % of it at ``p = 1``), and a 3x3 refinement of the bilinearly upsampled result concatenated with
the newest full-resolution map brings ``s_bev`` back to the lift's resolution (the students pool it 2 x 2 anyway). The first frames of an episode have no
history: the earliest available frame is repeated (the same rule in training, batch and streaming inference).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from pipeline.core.errors import ConfigError
from pretrain.geometry import (
    EVIDENCE_CHANNELS,
    BEVGrid,
    Camera,
    LiftGeometry,
    lift_evidence,
    lift_splat,
    relative_pose,
    sample_depth,
    warp_bev,
)

_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)
_STAGE_CHANNELS = {1: 64, 2: 128, 3: 256, 4: 512}
# the pretext targets, in the heads' channel order
TARGETS = ("static", "ped_t", "ped_t+0.5s", "ped_t+1.0s")


DECODERS = ("unet", "none")
# what an encoder.json written before a key existed means (the architecture it was trained with)
LEGACY_ENCODER = {"evidence": False, "decoder": "none", "fuse_pool": 1}


@dataclass
class EncoderConfig:
    """Architecture and geometry of the BEV encoder (saved with the checkpoint; consumers need nothing else)."""

    x_bound: list[float] = field(default_factory=lambda: [0.0, 6.0, 0.1])  # forward (min, max, step) m
    y_bound: list[float] = field(default_factory=lambda: [-4.8, 4.8, 0.1])  # lateral, left positive (min, max, step) m
    z_bound: list[float] = field(default_factory=lambda: [0.1, 2.0])  # kept heights (ground threshold, top) m
    bev_channels: int = 32  # C of x_bev and s_bev
    resnet_stages: int = 2  # ResNet-18 stages kept (1-4): feature stride 4, 8, 16, 32 px
    lift_stride_px: int = 4  # lift one pixel in every lift_stride_px x lift_stride_px block
    history_frames: int = 5  # T: frames in the temporal window, newest included (0.4 s at 10 Hz)
    backbone_weights: str = ""  # optional torchvision resnet18 state dict (.pth/.safetensors) to start from
    evidence: bool = True  # add the depth's per-cell evidence (hits / floor / free rays) to x_bev
    decoder: str = "unet"  # after the temporal model: "unet" (BEVDecoder, ~5 m receptive field) | "none"
    fuse_pool: int = 1  # warp + temporal model + decoder on p x p pooled maps, then refined back (module docstring)

    def validate(self) -> None:
        self.grid.validate("encoder")
        if self.resnet_stages not in _STAGE_CHANNELS:
            raise ConfigError(f"encoder.resnet_stages: expected 1-4, got {self.resnet_stages}")
        if self.decoder not in DECODERS:
            raise ConfigError(f"encoder.decoder: expected one of {list(DECODERS)}, got {self.decoder!r}")
        if not isinstance(self.evidence, bool):
            raise ConfigError(f"encoder.evidence: expected true or false, got {self.evidence!r}")
        for k in ("bev_channels", "lift_stride_px", "history_frames", "fuse_pool"):
            v = getattr(self, k)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ConfigError(f"encoder.{k}: expected an integer >= 1, got {v!r}")
        shape = self.grid.shape
        if any(n % self.fuse_pool for n in shape):
            raise ConfigError(f"encoder.fuse_pool: expected a divisor of both BEV grid sizes {list(shape)}, "
                              f"got {self.fuse_pool}")

    @property
    def grid(self) -> BEVGrid:
        return BEVGrid(tuple(self.x_bound), tuple(self.y_bound), tuple(self.z_bound))

    @property
    def fuse_grid(self) -> BEVGrid:
        """The grid the temporal model and the decoder run on (``grid`` with ``fuse_pool`` times larger cells)."""
        p = self.fuse_pool
        return BEVGrid((self.x_bound[0], self.x_bound[1], self.x_bound[2] * p),
                       (self.y_bound[0], self.y_bound[1], self.y_bound[2] * p), tuple(self.z_bound))


def _resnet18_trunk(stages: int) -> nn.Sequential:
    # lazy: torchvision's import pulls in torch._dynamo (≈ 4 s on the 2-core VM) — paid only where a trunk is built,
    # not by every process that reads checkpoints, targets or the grid
    from torchvision.models import resnet18

    m = resnet18(weights=None)
    layers: list[nn.Module] = [m.conv1, m.bn1, m.relu, m.maxpool, m.layer1, m.layer2, m.layer3, m.layer4]
    return nn.Sequential(*layers[: 4 + stages])


class TimeConv(nn.Module):
    """A causal 3D convolution with kernel ``2 x 3 x 3`` over ``B x C x T x X x Y`` → ``B x C x (T-1) x X x Y``.

    The weight is an ordinary ``Conv3d`` weight (``C_out x C_in x 2 x 3 x 3``), but the convolution is computed as
    one 2D convolution over channel-stacked consecutive frame pairs: mathematically identical (tested against
    ``F.conv3d``) and ~3.5x faster on a CPU, where PyTorch's Conv3d has no fast kernel (5 ms vs 18 ms at
    32 x 60 x 96, one thread).
    """

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(c_out, c_in, 2, 3, 3))
        nn.init.kaiming_uniform_(self.weight, a=5 ** 0.5)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, t = x.shape[:3]
        w2d = torch.cat([self.weight[:, :, 0], self.weight[:, :, 1]], 1)  # C_out x 2C_in x 3 x 3
        pairs = torch.cat([x[:, :, :-1], x[:, :, 1:]], 1).transpose(1, 2).flatten(0, 1)  # B(T-1) x 2C x X x Y
        y = F.conv2d(pairs, w2d, padding=1)
        return y.view(b, t - 1, *y.shape[1:]).transpose(1, 2)


class TemporalModel(nn.Module):
    """FIERY-style temporal model: ``B x T x C x X x Y`` aligned maps → ``B x C x X x Y``.

    T−1 causal blocks (:class:`TimeConv` + BatchNorm3d + ReLU) shrink the time axis to one step; a 1x1 skip from
    the newest map is added, then BatchNorm + ReLU.
    """

    def __init__(self, channels: int, frames: int) -> None:
        super().__init__()
        self.blocks = nn.ModuleList(
            nn.Sequential(TimeConv(channels, channels), nn.BatchNorm3d(channels), nn.ReLU(inplace=True))
            for _ in range(frames - 1))
        self.skip = nn.Conv2d(channels, channels, 1, bias=False)
        self.norm = nn.BatchNorm2d(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        newest = x[:, -1]
        y = x.transpose(1, 2)  # B C T X Y
        for block in self.blocks:
            y = block(y)  # the time axis shrinks by one per causal block
        out = self.skip(newest)
        if self.blocks:
            out = out + y[:, :, -1]
        return F.relu(self.norm(out))


def _conv_bn(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(c_out),
                         nn.ReLU(inplace=True))


class BEVDecoder(nn.Module):
    """A BEV encoder-decoder on ``B x C x X x Y`` (FIERY's decoder, smaller): three stride-2 stages (C → 2C → 2C →
    4C channels, two 3x3 convolutions each: receptive field ≈ 43 cells, 4.3 m at 0.1 m, before the upsampling
    path widens it), bilinear upsampling with skip connections back to full resolution, added to the input. The
    heads alone see ~1 m; this lets a cell's occupancy depend on the room around it (a wall's far side, a free
    corridor, where a person is heading)."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.down = nn.ModuleList([nn.Sequential(_conv_bn(a, b, 2), _conv_bn(b, b))
                                   for a, b in ((c, 2 * c), (2 * c, 2 * c), (2 * c, 4 * c))])
        self.up = nn.ModuleList([_conv_bn(4 * c + 2 * c, 2 * c), _conv_bn(2 * c + 2 * c, 2 * c),
                                 _conv_bn(2 * c + c, c)])
        self.out = nn.Sequential(nn.Conv2d(c, c, 1, bias=False), nn.BatchNorm2d(c))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips, y = [x], x
        for stage in self.down:
            y = stage(y)
            skips.append(y)
        skips.pop()  # the bottom is y itself
        for stage in self.up:
            skip = skips.pop()
            y = stage(torch.cat([F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False), skip],
                                1))
        return F.relu(x + self.out(y))


class BEVEncoder(nn.Module):
    """The spatio-temporal encoder: RGB-D window → ``s_bev`` (see the module docstring for shapes)."""

    def __init__(self, cfg: EncoderConfig, cameras: list[Camera]) -> None:
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.cameras = list(cameras)
        self.grid = cfg.grid
        self.trunk = _resnet18_trunk(cfg.resnet_stages)
        self.neck = nn.Sequential(nn.Conv2d(_STAGE_CHANNELS[cfg.resnet_stages], cfg.bev_channels, 1, bias=False),
                                  nn.BatchNorm2d(cfg.bev_channels), nn.ReLU(inplace=True))
        self.temporal = TemporalModel(cfg.bev_channels, cfg.history_frames)
        if cfg.evidence:
            self.evidence = nn.Conv2d(len(EVIDENCE_CHANNELS), cfg.bev_channels, 1)
        if cfg.decoder == "unet":
            self.decoder = BEVDecoder(cfg.bev_channels)
        self.fuse_grid = cfg.fuse_grid
        if cfg.fuse_pool > 1:
            self.refine = _conv_bn(2 * cfg.bev_channels, cfg.bev_channels)
        self.geom = LiftGeometry(self.cameras, cfg.lift_stride_px)
        self.register_buffer("mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    @property
    def frames(self) -> int:
        return self.cfg.history_frames

    @property
    def out_shape(self) -> tuple[int, int, int]:
        """``(C, X, Y)`` of ``s_bev``."""
        return (self.cfg.bev_channels, *self.grid.shape)

    def normalize(self, rgb: torch.Tensor) -> torch.Tensor:
        """``M x 3 x H x W`` images (uint8 or float in [0, 1]) → the trunk's ImageNet-normalised input."""
        x = rgb.float() / 255.0 if rgb.dtype == torch.uint8 else rgb
        return (x - self.mean) / self.std

    def image_features(self, rgb: torch.Tensor) -> torch.Tensor:
        """``M x 3 x H x W`` images (uint8 or float in [0, 1]) → ``M x C x h x w`` features at the lift pixels."""
        x = self.normalize(rgb)
        if not self.training:
            # inference channels-last through the trunk: this torch's CPU max-pool (the stem's) is ≈ 15x slower on
            # NCHW (5.5 vs 0.35 ms at 2 x 64 x 60 x 80, one thread) and mkldnn convolves channels-last without
            # reordering — the streaming step 1.14x (docs/results.md, Performance). Training keeps NCHW: the one
            # pretraining run with channels-last left an encoder whose int8 version lost its static map
            # (docs/notes/2026-12-channels-last-trunk.md)
            x = x.contiguous(memory_format=torch.channels_last)
        # float32 and contiguous out: under bf16 autocast (pretrain.precision) the geometry that follows stays float32
        f = self.neck(self.trunk(x)).float().contiguous()
        if tuple(f.shape[-2:]) != tuple(self.geom.lift_hw):
            f = F.interpolate(f, size=tuple(self.geom.lift_hw), mode="bilinear", align_corners=False)
        return f

    def encode_frames(self, rgb: torch.Tensor, depth_lift: torch.Tensor) -> torch.Tensor:
        """One BEV map per frame.

        Args:
            rgb: ``M x N x 3 x H x W`` images of M frames.
            depth_lift: ``M x N x h x w`` depth at the lift pixels (:meth:`lift_depth` of the full image).

        Returns:
            ``M x C x X x Y`` maps, each in its own frame's base frame.
        """
        m, n = rgb.shape[:2]
        if n != len(self.cameras):
            raise ValueError(f"expected {len(self.cameras)} cameras, got {n}")
        feats = self.image_features(rgb.flatten(0, 1))
        feats = feats.view(m, n, *feats.shape[1:])
        x = lift_splat(feats, depth_lift.float(), self.geom, self.grid)
        if self.cfg.evidence:
            x = x + self.evidence(lift_evidence(depth_lift, self.geom, self.grid))
        return x

    def lift_depth(self, depth: torch.Tensor) -> torch.Tensor:
        """Full-resolution depth ``... x H x W`` → depth at the lift pixels ``... x h x w``."""
        return sample_depth(depth, self.cfg.lift_stride_px)

    def pool(self, maps: torch.Tensor) -> torch.Tensor:
        """``... x C x X x Y`` maps → the same on :attr:`fuse_grid` (``fuse_pool`` x ``fuse_pool`` averages; the
        maps themselves when ``fuse_pool`` is 1). Per frame, so a stream can pool each frame once and cache it."""
        p = self.cfg.fuse_pool
        if p == 1:
            return maps
        return F.avg_pool2d(maps.flatten(0, -4), p).view(*maps.shape[:-2], *self.fuse_grid.shape)

    def fuse(self, maps: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """Warps a window of maps into its newest frame and runs the temporal model.

        Args:
            maps: ``B x T x C x X x Y``, each in its own frame.
            poses: ``B x T x 3`` the frames' world poses.

        Returns:
            ``B x C x X x Y`` = ``s_bev``.
        """
        return self.fuse_pooled(self.pool(maps), maps[:, -1], poses)

    def fuse_pooled(self, window: torch.Tensor, newest: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """:meth:`fuse` on a window already :meth:`pool`-ed (``B x T x C x X' x Y'``) and the newest frame's
        full-resolution map ``newest`` ``B x C x X x Y`` (used only when ``fuse_pool`` > 1)."""
        b, t = window.shape[:2]
        if t != self.frames:
            raise ValueError(f"expected a window of {self.frames} frames, got {t}")
        newest_pose = poses[:, -1:].expand(b, t - 1, 3)
        rel = relative_pose(poses[:, :-1].double(), newest_pose.double()).float()
        past = warp_bev(window[:, :-1].flatten(0, 1), rel.flatten(0, 1), self.fuse_grid) if t > 1 else window[:, :0]
        aligned = torch.cat([past.view(b, t - 1, *window.shape[2:]), window[:, -1:]], 1)
        return self.fuse_aligned(aligned, newest)

    def fuse_aligned(self, aligned: torch.Tensor, newest: torch.Tensor) -> torch.Tensor:
        """The dense part of :meth:`fuse_pooled`: a window already warped into its newest frame
        (``B x T x C x X' x Y'``) → temporal model → decoder → (``fuse_pool`` > 1) upsampling and refinement with the
        newest full-resolution map → ``s_bev``. All convolutions, no geometry (what :mod:`pretrain.quantize` runs in
        int8)."""
        s_bev = self.temporal(aligned)
        if self.cfg.decoder == "unet":
            s_bev = self.decoder(s_bev)
        if self.cfg.fuse_pool == 1:
            return s_bev.float()
        up = F.interpolate(s_bev, size=tuple(self.grid.shape), mode="bilinear", align_corners=False)
        return self.refine(torch.cat([up.float(), newest], 1)).float()  # float32 out (see image_features)

    def forward(self, rgb: torch.Tensor, depth: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """Batch forward: ``B x T`` windows (full-resolution depth) → ``s_bev`` ``B x C x X x Y``."""
        b, t = rgb.shape[:2]
        maps = self.encode_frames(rgb.flatten(0, 1), self.lift_depth(depth.flatten(0, 1)))
        return self.fuse(maps.view(b, t, *maps.shape[1:]), poses)

    def describe(self) -> dict[str, Any]:
        return {"encoder": {k: getattr(self.cfg, k) for k in self.cfg.__dataclass_fields__},
                "cameras": [c.to_dict() for c in self.cameras], "s_bev_shape": list(self.out_shape)}


class BEVStream:
    """Step-wise inference: encodes only the newest frame and reuses the cached history.

    The cache holds the last T−1 maps *in their own frames* with their poses, already pooled to the encoder's
    fusion grid (each frame pooled once, when it arrives); every step warps them into the new frame (one
    ``grid_sample``), so the result equals :meth:`BEVEncoder.forward` on the same window exactly, and warping errors
    never accumulate. Works for a batch of B independent streams (vectorised environments).
    """

    def __init__(self, encoder: BEVEncoder) -> None:
        self.encoder = encoder
        self.maps: torch.Tensor | None = None  # B x (T-1) x C x X' x Y' (pooled: BEVEncoder.pool)
        self.poses: torch.Tensor | None = None  # B x (T-1) x 3

    def reset(self) -> None:
        """Forgets every stream's history (the next step starts new episodes)."""
        self.maps = self.poses = None

    @torch.no_grad()
    def step(self, rgb: torch.Tensor, depth: torch.Tensor, pose: torch.Tensor,
             first: torch.Tensor | None = None) -> torch.Tensor:
        """Encodes one new frame per stream.

        Args:
            rgb: ``B x N x 3 x H x W`` images.
            depth: ``B x N x H x W`` full-resolution depth (m).
            pose: ``B x 3`` world poses.
            first: ``B`` bool, True where this frame starts a new episode (its history is this frame repeated).

        Returns:
            ``B x C x X x Y`` = ``s_bev`` of the newest frames.
        """
        enc = self.encoder
        pose = pose.to(torch.float64)
        full = enc.encode_frames(rgb, enc.lift_depth(depth))  # B C X Y
        x = enc.pool(full)  # B C X' Y'
        b, t = x.shape[0], enc.frames
        rep_maps = x.unsqueeze(1).expand(b, t - 1, *x.shape[1:])
        rep_poses = pose.unsqueeze(1).expand(b, t - 1, 3)
        if self.maps is None or self.maps.shape[0] != b:  # no (matching) history: every stream starts here
            self.maps, self.poses = rep_maps.clone(), rep_poses.clone()
        elif first is not None and bool(first.any()):
            self.maps = torch.where(first.view(b, 1, 1, 1, 1), rep_maps, self.maps)
            self.poses = torch.where(first.view(b, 1, 1), rep_poses, self.poses)
        window = torch.cat([self.maps, x.unsqueeze(1)], 1)
        poses = torch.cat([self.poses, pose.unsqueeze(1)], 1)
        out = enc.fuse_pooled(window, full, poses)
        self.maps, self.poses = window[:, 1:], poses[:, 1:]
        return out


class PretextHeads(nn.Module):
    """Occupancy logits from ``s_bev``: ``B x C x X x Y`` → ``B x len(TARGETS) x X x Y`` (see :data:`TARGETS`)."""

    def __init__(self, channels: int, outputs: int = len(TARGETS)) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(channels, channels, 3, padding=1, bias=False), nn.BatchNorm2d(channels),
                                  nn.ReLU(inplace=True), nn.Conv2d(channels, channels, 3, padding=1, bias=False),
                                  nn.BatchNorm2d(channels))
        self.out = nn.Conv2d(channels, outputs, 1)

    def forward(self, s_bev: torch.Tensor) -> torch.Tensor:
        return self.out(F.relu(s_bev + self.body(s_bev)))
