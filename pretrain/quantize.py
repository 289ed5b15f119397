"""Post-training static int8 quantization of the frozen BEV encoder, for CPU inference.

A rendered student's step on the 2-core CPU is dominated by the frozen encoder (≈ 39 of ≈ 74 ms per step at
160 × 120, one thread: the ResNet trunk ≈ 18 ms, the temporal model + decoder + refinement ≈ 17 ms; docs/results.md,
Performance). Both are stacks of convolutions, which x86 CPUs run several times faster in int8 (oneDNN / FBGEMM
kernels) than in float32. This module quantizes exactly those two parts with PyTorch's FX graph-mode post-training
static quantization (``torch.ao.quantization``: per-channel int8 weights, per-tensor uint8 activations whose ranges
come from histogram observers run on calibration frames, the ``x86`` backend); the geometry — lifting, splatting,
the depth evidence, pooling and warping — stays float32, so the int8 encoder consumes and produces exactly what the
float one does (same shapes, same frames), only with the quantization error of its convolutions.

What we write ourselves and why: the two traceable float modules (:class:`ImageNet`, :class:`DenseFuse`) that
restate the encoder's dense parts without data-dependent Python (the temporal model's causal 3-D convolutions as
2-D convolutions over channel-stacked frame pairs, mathematically the same as :class:`pretrain.model.TimeConv`),
and the storage of a calibration: the activation observers' state (a few kB of histograms) in one safetensors file,
so a quantized encoder is rebuilt bit-identically from the float checkpoint and that file, with no pickled graph.

The calibration is deterministic given the float weights and the calibration frames (histogram observers, no
randomness), and so is the quantized encoder built from it.

The third inference precision, ``bf16`` (:class:`BF16BEVEncoder`), needs no calibration: the same two dense parts
run in bfloat16 (BatchNorms folded into their convolutions, bfloat16 channels-last weights; on a CPU with
AVX512-BF16 or AMX, or a GPU), the geometry and the output in float32. Its error against float32 is ≈ 0.3 % of
``s_bev``'s norm (int8: several times more), at ≈ 2× the float32 speed on one CPU thread (docs/results.md,
Performance).
"""

from __future__ import annotations

import copy
import json
import math
import warnings
from collections.abc import Iterable
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn
from torch.fx.experimental.optimization import fuse as fx_fuse
from torch.nn.utils.fusion import fuse_conv_bn_eval

with warnings.catch_warnings():  # torch >= 2.9 announces on import that FX quantization moves to torchao
    warnings.simplefilter("ignore")
    from torch.ao.quantization import get_default_qconfig_mapping
    from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx

from pipeline.core.device import native_bf16
from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from pretrain.checkpoint import METRICS_JSON, load_encoder, read_weights, save_tensors
from pretrain.model import BEVEncoder

PRECISIONS = ("auto", "fp32", "bf16", "int8")  # auto: bf16 where the device has native bfloat16, else fp32
CALIBRATION_FILE = "int8_calibration.safetensors"
BACKEND = "x86"
# the validation IoU (any pretext target, absolute) an int8 version may lose against its float encoder and still be
# used: the int8 versions that worked lost <= 0.005, the two that failed 0.21 of the static map (docs/notes/
# 2026-12-int8-encoder.md); `make pretrain` scores both on the validation frames and writes them to metrics.json
INT8_MAX_IOU_DROP = 0.05


class ImageNet(nn.Module):
    """The encoder's image branch after normalisation: trunk → neck → (resize to the lift pixels)."""

    def __init__(self, enc: BEVEncoder, x: torch.Tensor) -> None:
        """A copy of ``enc``'s trunk and neck for normalised images shaped like ``x`` (whether their features need
        resizing to the lift pixels is decided on ``x``: FX traces with concrete shapes)."""
        super().__init__()
        self.trunk = copy.deepcopy(enc.trunk)
        self.neck = copy.deepcopy(enc.neck)
        self.lift_hw = tuple(int(v) for v in enc.geom.lift_hw)
        with torch.no_grad():
            self.resize = tuple(self.neck(self.trunk(x[:1])).shape[-2:]) != self.lift_hw

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = self.neck(self.trunk(x))
        if self.resize:
            f = F.interpolate(f, size=self.lift_hw, mode="bilinear", align_corners=False)
        return f


class DenseFuse(nn.Module):
    """:meth:`BEVEncoder.fuse_aligned` as a traceable module: the temporal model's causal blocks as 2-D convolutions
    over channel-stacked consecutive frames (+ BatchNorm + ReLU), the newest frame's 1x1 skip, the decoder, and —
    with ``fuse_pool`` > 1 — the upsampling and refinement with the newest full-resolution map."""

    def __init__(self, enc: BEVEncoder) -> None:
        super().__init__()
        tm = enc.temporal
        self.frames = enc.frames
        self.blocks = nn.ModuleList()
        for block in tm.blocks:
            time_conv, bn3 = block[0], block[1]
            w = time_conv.weight.detach()
            conv = nn.Conv2d(2 * w.shape[1], w.shape[0], 3, padding=1, bias=False)
            conv.weight.data.copy_(torch.cat([w[:, :, 0], w[:, :, 1]], 1))
            bn = nn.BatchNorm2d(bn3.num_features, eps=bn3.eps, momentum=bn3.momentum)
            bn.load_state_dict(bn3.state_dict())
            self.blocks.append(nn.Sequential(conv, bn, nn.ReLU()))
        self.skip = copy.deepcopy(tm.skip)
        self.norm = copy.deepcopy(tm.norm)
        self.decoder = copy.deepcopy(enc.decoder) if enc.cfg.decoder == "unet" else None
        self.refine = copy.deepcopy(enc.refine) if enc.cfg.fuse_pool > 1 else None
        self.grid_hw = tuple(int(v) for v in enc.grid.shape)

    def forward(self, aligned: torch.Tensor, newest: torch.Tensor) -> torch.Tensor:
        maps = [aligned[:, i] for i in range(self.frames)]
        last = maps[-1]
        for block in self.blocks:  # the time axis shrinks by one per causal block
            maps = [block(torch.cat([maps[i], maps[i + 1]], 1)) for i in range(len(maps) - 1)]
        out = self.skip(last)
        if len(self.blocks):
            out = out + maps[-1]
        s_bev = F.relu(self.norm(out))
        if self.decoder is not None:
            s_bev = self.decoder(s_bev)
        if self.refine is None:
            return s_bev
        up = F.interpolate(s_bev, size=self.grid_hw, mode="bilinear", align_corners=False)
        return self.refine(torch.cat([up, newest], 1))


class _FrozenCopy(BEVEncoder):
    """A frozen copy of a float :class:`BEVEncoder` (same config, cameras and weights; ``eval()``, no gradients)
    whose subclasses change how its dense parts compute; ``state_dict`` stays the float encoder's, so
    :mod:`pretrain.checkpoint` treats it as the encoder it came from."""

    def __init__(self, encoder: BEVEncoder) -> None:
        super().__init__(encoder.cfg, encoder.cameras)
        self.load_state_dict(encoder.state_dict())
        self.eval().requires_grad_(False)


class BF16BEVEncoder(_FrozenCopy):
    """A :class:`BEVEncoder` whose image branch and dense fusion (the parts :class:`QuantizedBEVEncoder` runs in
    int8) run in bfloat16 on their inputs' device; lifting, splatting, warping and ``s_bev`` stay float32
    (:meth:`BEVEncoder.image_features` and :meth:`BEVEncoder.fuse_aligned` return float32). Inference only; the
    weights (``state_dict``) are the float encoder's, unchanged.

    The two parts are prepared once, on their first call: every BatchNorm folded into the convolution before it
    (torch's ``fuse_conv_bn_eval``; FX's ``fuse`` for the trunk, whose modules each run once), the weights cast to
    bfloat16 and laid out channels-last. Against the same parts under bfloat16 autocast (this class before) that
    removes a weight cast per convolution per call and every BatchNorm: the streaming step 1.4x (one episode) and
    1.6x (a DAgger rollout's episode and its mirror) faster on a CPU thread, with a smaller error against float32
    (0.34 vs 0.40 % of ``s_bev``'s norm; docs/results.md, Performance)."""

    def __init__(self, encoder: BEVEncoder) -> None:
        super().__init__(encoder)
        # built on first use, outside the module tree: state_dict and .to() see the float encoder only
        self._bf16: dict[str, nn.Module] = {}

    def _drop_prepared(self) -> None:
        if "_bf16" in self.__dict__:  # not yet during __init__ (which loads the weights)
            self._bf16.clear()

    def _apply(self, fn, recurse=True):
        """``.to()`` / ``.cuda()`` / a dtype cast after first use: the prepared parts are rebuilt from the moved
        float weights on the next call (they are outside the module tree, so torch would not move them)."""
        self._drop_prepared()
        return super()._apply(fn, recurse)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """New float weights after first use: the prepared parts are rebuilt from them on the next call."""
        self._drop_prepared()
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def _part(self, name: str, build) -> nn.Module:
        part = self._bf16.get(name)
        if part is None:
            part = self._bf16[name] = build().to(dtype=torch.bfloat16, memory_format=torch.channels_last)
        return part

    def image_features(self, rgb: torch.Tensor) -> torch.Tensor:
        x = self.normalize(rgb).contiguous(memory_format=torch.channels_last)
        net = self._part("image", lambda: fx_fuse(ImageNet(self, x).eval()))
        return net(x.to(torch.bfloat16)).float().contiguous()

    def fuse_aligned(self, aligned: torch.Tensor, newest: torch.Tensor) -> torch.Tensor:
        net = self._part("dense", lambda: fold_batch_norms(DenseFuse(self).eval()))
        return net(aligned.to(torch.bfloat16), newest.to(torch.bfloat16)).float()


def fold_batch_norms(module: nn.Module) -> nn.Module:
    """``module`` (in eval mode) with every ``Conv2d`` → ``BatchNorm2d`` pair inside an ``nn.Sequential`` replaced
    by the one convolution that computes both (torch's ``fuse_conv_bn_eval``), in place. For modules that call a
    submodule more than once (:class:`DenseFuse`'s causal blocks), where FX's graph-level ``fuse`` would fold a
    shared BatchNorm once per call."""
    for child in module.children():
        fold_batch_norms(child)
    if isinstance(module, nn.Sequential):
        for i in range(len(module) - 1):
            if isinstance(module[i], nn.Conv2d) and isinstance(module[i + 1], nn.BatchNorm2d):
                module[i], module[i + 1] = fuse_conv_bn_eval(module[i], module[i + 1]), nn.Identity()
    return module


def _prepare(module: nn.Module, example: tuple[torch.Tensor, ...], mapping=None) -> nn.Module:
    """FX-prepares ``module`` for calibration with ``mapping`` (a ``QConfigMapping``; default: the backend's)."""
    torch.backends.quantized.engine = BACKEND
    with warnings.catch_warnings():  # torch >= 2.9 warns that FX quantization moves to torchao
        warnings.simplefilter("ignore")
        return prepare_fx(module.eval(), get_default_qconfig_mapping(BACKEND) if mapping is None else mapping, example)


def _convert(prepared: nn.Module) -> nn.Module:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return convert_fx(prepared)


class QuantizedBEVEncoder(_FrozenCopy):
    """A :class:`BEVEncoder` whose image branch and dense fusion run in int8 (module docstring). Built from a float
    encoder; :meth:`calibrate` feeds it calibration frames (it computes the float results meanwhile), :meth:`freeze`
    converts it. Used for inference only; the float weights stay inside."""

    def __init__(self, encoder: BEVEncoder) -> None:
        super().__init__(encoder)
        self._image_q: nn.Module | None = None
        self._dense_q: nn.Module | None = None
        self.frozen = False

    # the two dense parts: observed (calibrating) or int8 (frozen); prepared lazily on the first call's shapes
    def image_features(self, rgb: torch.Tensor) -> torch.Tensor:
        x = self.normalize(rgb)
        if self._image_q is None:
            self._image_q = _prepare(ImageNet(self, x), (x,))
        return self._image_q(x)

    def fuse_aligned(self, aligned: torch.Tensor, newest: torch.Tensor) -> torch.Tensor:
        if self._dense_q is None:
            self._dense_q = _prepare(DenseFuse(self), (aligned, newest))
        return self._dense_q(aligned, newest)

    @torch.no_grad()
    def calibrate(self, windows: Iterable[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]) -> int:
        """Runs ``(rgb B x T x N x 3 x H x W, depth B x T x N x H x W, poses B x T x 3)`` windows through the encoder
        (:meth:`forward`), the observers recording the ranges of every activation; returns the number of windows."""
        if self.frozen:
            raise RuntimeError("calibrate: this encoder is already converted to int8")
        n = 0
        for rgb, depth, poses in windows:
            self(rgb, depth, poses)
            n += 1
        if n == 0:
            raise ConfigError("int8 calibration: expected at least one calibration window, got none")
        return n

    def freeze(self) -> QuantizedBEVEncoder:
        """Converts the observed parts to int8 (after :meth:`calibrate` or :meth:`load_calibration`)."""
        if self._image_q is None or self._dense_q is None:
            raise ConfigError("int8 encoder: calibrate (or load a calibration) before converting")
        if not self.frozen:
            self._image_q, self._dense_q = _convert(self._image_q), _convert(self._dense_q)
            self.frozen = True
        return self

    def calibration_state(self) -> dict[str, torch.Tensor]:
        """The activation observers' state (names → tensors): what :meth:`load_calibration` needs."""
        if self.frozen or self._image_q is None or self._dense_q is None:
            raise RuntimeError("calibration_state: only a calibrated, not yet converted encoder has observers")
        out = {}
        for part, mod in (("image", self._image_q), ("dense", self._dense_q)):
            for k, v in mod.state_dict().items():
                if "activation_post_process" in k:
                    out[f"{part}.{k}"] = v.detach().clone().contiguous()
        return out

    def load_calibration(self, state: dict[str, torch.Tensor], example: tuple[torch.Tensor, ...],
                         where: str = "int8 calibration") -> QuantizedBEVEncoder:
        """Prepares the two parts on ``example`` = ``(rgb, depth, poses)`` of one window (shapes only), loads the
        observers' ``state`` and converts; ``where`` names the source in errors."""
        with torch.no_grad():
            self._image_q = self._dense_q = None
            self(*example)  # prepares both parts on these shapes (their observers then overwritten below)
            expected = {f"{part}.{k}" for part, mod in (("image", self._image_q), ("dense", self._dense_q))
                        for k in mod.state_dict() if "activation_post_process" in k}
            if set(state) != expected:
                missing, extra = sorted(expected - set(state))[:3], sorted(set(state) - expected)[:3]
                raise CorruptArtifactError(f"{where}: the calibration does not match this encoder's architecture "
                                           f"(missing {missing}, unexpected {extra}); re-run the calibration")
            for part, mod in (("image", self._image_q), ("dense", self._dense_q)):
                sub = {k[len(part) + 1:]: v for k, v in state.items() if k.startswith(part + ".")}
                own = mod.state_dict()
                own.update(sub)
                mod.load_state_dict(own)
        return self.freeze()


def quantize_encoder(encoder: BEVEncoder, windows: Iterable[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
                     ) -> tuple[QuantizedBEVEncoder, dict[str, torch.Tensor]]:
    """The int8 encoder of ``encoder`` calibrated on ``windows`` (:meth:`QuantizedBEVEncoder.calibrate`) and its
    calibration state (to save with :func:`save_calibration`)."""
    q = QuantizedBEVEncoder(encoder)
    q.calibrate(windows)
    state = q.calibration_state()
    return q.freeze(), state




def example_window(encoder: BEVEncoder, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A blank ``(rgb, depth, poses)`` window of the encoder's cameras (shapes only: what preparing needs)."""
    cams, t = encoder.cameras, encoder.frames
    h, w = int(cams[0].height), int(cams[0].width)
    return (torch.zeros(batch, t, len(cams), 3, h, w, dtype=torch.uint8), torch.zeros(batch, t, len(cams), h, w),
            torch.zeros(batch, t, 3, dtype=torch.float64))


def save_calibration(ckpt: Path, state: dict[str, torch.Tensor], meta: dict[str, str]) -> Path:
    """Writes the calibration ``state`` (:meth:`QuantizedBEVEncoder.calibration_state`) beside the encoder's
    weights (``<ckpt>/int8_calibration.safetensors``, atomically); returns the path."""
    path = Path(ckpt) / CALIBRATION_FILE
    save_tensors(state, path, {"backend": BACKEND, **meta})
    return path


def int8_iou_losses(metrics: dict) -> dict[str, tuple[float, float]]:
    """The pretext targets whose int8 validation IoU in a pretraining's ``metrics`` (``metrics.json``: ``final`` the
    float encoder's, ``int8`` its int8 version's) is more than :data:`INT8_MAX_IOU_DROP` below the float one's:
    ``iou_<target>`` → ``(float, int8)``. Empty when the int8 version keeps the maps, or was not scored."""
    final, int8 = metrics.get("final") or {}, metrics.get("int8") or {}
    out = {}
    for k, f in final.items():
        q = int8.get(k)
        if not k.startswith("iou_") or not isinstance(f, (int, float)) or not isinstance(q, (int, float)):
            continue
        if math.isfinite(f) and (not math.isfinite(q) or f - q > INT8_MAX_IOU_DROP):
            out[k] = (float(f), float(q))
    return out


def check_int8_version(ckpt: Path) -> None:
    """Refuses an int8 version that its pretraining's validation showed to lose the maps (:func:`int8_iou_losses`
    on ``<ckpt>/metrics.json``; a checkpoint without that file or its ``int8`` scores passes unchecked).

    Raises:
        ConfigError: naming the file, the field, the float and the int8 IoU and the allowed loss.
        CorruptArtifactError: ``metrics.json`` is not JSON.
    """
    path = Path(ckpt) / METRICS_JSON
    if not path.is_file():
        return
    try:
        metrics = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CorruptArtifactError(f"{path}: not readable JSON ({e}); re-run `make pretrain`") from e
    losses = int8_iou_losses(metrics if isinstance(metrics, dict) else {})
    if losses:
        k, (f, q) = max(losses.items(), key=lambda kv: kv[1][0] - kv[1][1])
        raise ConfigError(f"encoder_precision int8: the int8 version of {ckpt} loses the pretext maps on its "
                          f"validation frames ({path}: int8.{k} {q:.3f} against final.{k} {f:.3f}, expected a "
                          f"loss <= {INT8_MAX_IOU_DROP}); use encoder_precision fp32, bf16 or auto with this "
                          "encoder")


def load_int8_encoder(ckpt: Path, encoder: BEVEncoder) -> QuantizedBEVEncoder:
    """The int8 version of ``encoder`` (loaded from ``ckpt``) from the calibration saved beside it, if its
    pretraining's validation did not show it to lose the maps (:func:`check_int8_version`).

    Raises:
        ConfigError: the int8 version loses more than :data:`INT8_MAX_IOU_DROP` of validation IoU.
        InputMissingError: ``ckpt`` has no calibration (a checkpoint of code before int8 inference: re-run
            ``make pretrain``). CorruptArtifactError: unreadable, not matching its manifest, or another architecture.
    """
    path = Path(ckpt) / CALIBRATION_FILE
    if not path.is_file():
        raise InputMissingError(f"no int8 calibration {path} for encoder_precision int8: the BEV checkpoint predates "
                                "int8 inference (re-run `make pretrain`), or use encoder_precision fp32")
    check_int8_version(ckpt)
    state = read_weights(path, hint="re-run `make pretrain` to write it again")
    q = QuantizedBEVEncoder(encoder)
    return q.load_calibration({k: v for k, v in state.items()}, example_window(encoder), where=str(path))


def load_frozen_encoder(ckpt: Path, precision: str = "fp32", device: torch.device | str = "cpu") -> BEVEncoder:
    """The frozen pretrained encoder of ``ckpt`` (:func:`pretrain.checkpoint.load_encoder`) at ``precision`` on
    ``device``: ``fp32``; ``bf16`` — its convolutions under bfloat16 autocast (:class:`BF16BEVEncoder`); ``int8``
    — its convolutions quantized with the calibration saved beside it (CPU inference only); or ``auto`` — bf16 where
    ``device`` has native bfloat16, else fp32 (:func:`resolve_encoder_precision`).

    Raises:
        ConfigError: an unknown precision, or one ``device`` does not run (:func:`check_precision`).
    """
    precision = resolve_encoder_precision(precision, "encoder precision", device)
    encoder = load_encoder(Path(ckpt), frozen=True)
    if precision == "int8":
        return load_int8_encoder(ckpt, encoder)
    return (BF16BEVEncoder(encoder) if precision == "bf16" else encoder).to(device)


def resolve_encoder_precision(value: str, where: str, device: torch.device | str) -> str:
    """The concrete precision (``fp32`` | ``bf16`` | ``int8``) that ``value`` names for an encoder on ``device``:
    ``auto`` is ``bf16`` where ``device`` computes bfloat16 natively (:func:`pipeline.core.device.native_bf16`: a CPU
    with AVX512-BF16 or AMX, an Ampere-or-later GPU), else ``fp32``; any other value as :func:`check_precision`
    accepts it (a ConfigError naming ``where`` otherwise)."""
    check_precision(value, where, device)
    if value == "auto":
        return "bf16" if native_bf16(device) else "fp32"
    return value


def check_precision(value: str, where: str, device: torch.device | str | None = None) -> str:
    """``value`` if it is one of :data:`PRECISIONS` (and, given the ``device`` the encoder will run on, one that
    device runs: ``int8`` only on a CPU, ``bf16`` only where bfloat16 is native), else a ConfigError naming
    ``where``."""
    if value not in PRECISIONS:
        raise ConfigError(f"{where}: expected one of {list(PRECISIONS)}, got {value!r}")
    if device is not None:
        device = torch.device(device)
        if value == "int8" and device.type != "cpu":
            raise ConfigError(f"{where}: int8 runs on the CPU only, got device {device}; use fp32 or bf16 there")
        if value == "bf16" and not native_bf16(device):
            raise ConfigError(f"{where}: expected fp32, int8 or auto on {device}, got 'bf16': this device has no "
                              "native bfloat16 (a CPU without AVX512-BF16 or AMX, or an older GPU), where it is emulated and "
                              "slower than float32")
    return value
