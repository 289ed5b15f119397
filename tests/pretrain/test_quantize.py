"""Tests of pretrain.quantize: the traceable restatement of the dense parts equals the float encoder, the int8
encoder stays close to it and streams, its calibration round-trips bit-identically through the file, and bad
calibrations are named (tiny cameras and grid of test_model, eval mode)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

import pretrain.quantize as quantize
from pipeline.core.device import native_bf16
from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from pretrain.checkpoint import METRICS_JSON, save_tensors, write_encoder_checkpoint
from pretrain.model import BEVEncoder, BEVStream, PretextHeads
from pretrain.quantize import (
    CALIBRATION_FILE,
    BF16BEVEncoder,
    DenseFuse,
    QuantizedBEVEncoder,
    check_precision,
    fold_batch_norms,
    int8_iou_losses,
    load_frozen_encoder,
    load_int8_encoder,
    quantize_encoder,
    resolve_encoder_precision,
    save_calibration,
)
from tests.pretrain.test_model import L, cameras, sequence, tiny_config

pytestmark = pytest.mark.usefixtures("one_thread")  # conftest; so is the `encoder` fixture


def windows(enc: BEVEncoder, n: int, seed: int, b: int = 2):
    rgb, depth, poses = sequence(b * n, seed)
    t = enc.frames
    return [(rgb[i * b:(i + 1) * b, :t], depth[i * b:(i + 1) * b, :t], poses[i * b:(i + 1) * b, :t])
            for i in range(n)]


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().mean() / b.abs().mean())


def test_the_traceable_dense_part_equals_the_encoders(encoder):
    """DenseFuse restates fuse_aligned (the causal 3-D blocks as 2-D convolutions over stacked pairs)."""
    g = torch.Generator().manual_seed(3)
    c = encoder.cfg.bev_channels
    x, y = encoder.fuse_grid.shape
    aligned = torch.relu(torch.randn(2, encoder.frames, c, x, y, generator=g))
    newest = torch.relu(torch.randn(2, c, *encoder.grid.shape, generator=g))
    with torch.no_grad():
        assert torch.allclose(DenseFuse(encoder).eval()(aligned, newest), encoder.fuse_aligned(aligned, newest),
                              atol=1e-5, rtol=1e-5)


def test_folding_the_batch_norms_keeps_the_dense_parts_outputs(encoder):
    """fold_batch_norms (the bf16 encoder's preparation) computes what the unfolded parts compute — DenseFuse calls
    each causal block once per frame pair, so a BatchNorm folded once per call would show here — with no BatchNorm
    left."""
    import copy

    enc = copy.deepcopy(encoder)
    g = torch.Generator().manual_seed(5)
    for m in enc.modules():  # statistics far from the identity, so a missed or doubled fold changes the output
        if isinstance(m, (torch.nn.BatchNorm2d, torch.nn.BatchNorm3d)):
            m.running_mean.copy_(torch.randn(m.num_features, generator=g))
            m.running_var.copy_(torch.rand(m.num_features, generator=g) + 0.5)
            m.weight.data.copy_(torch.randn(m.num_features, generator=g))
    c = enc.cfg.bev_channels
    aligned = torch.relu(torch.randn(2, enc.frames, c, *enc.fuse_grid.shape, generator=g))
    newest = torch.relu(torch.randn(2, c, *enc.grid.shape, generator=g))
    dense = DenseFuse(enc).eval()
    with torch.no_grad():
        ref = dense(aligned, newest)
        folded = fold_batch_norms(dense)
        assert torch.allclose(folded(aligned, newest), ref, atol=1e-4, rtol=1e-4)
    left = [m for m in folded.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert left == [folded.norm]  # the one after the skip's sum, which follows no convolution


def test_int8_encoder_is_close_to_float_and_streams_like_the_batch_forward(encoder):
    q, _ = quantize_encoder(encoder, windows(encoder, 4, seed=10))
    assert q.frozen and not q.training
    rgb, depth, poses = sequence(2, seed=20)
    t = encoder.frames
    with torch.no_grad():
        batch_q, batch_f = q(rgb[:, :t], depth[:, :t], poses[:, :t]), encoder(rgb[:, :t], depth[:, :t], poses[:, :t])
        assert batch_q.shape == batch_f.shape
        assert 0 < rel_err(batch_q, batch_f) < 0.15  # quantized, but the same function
        stream = BEVStream(q)
        for k in range(L):
            out = stream.step(rgb[:, k], depth[:, k], poses[:, k])
        last = q(rgb[:, L - t:], depth[:, L - t:], poses[:, L - t:])
    assert torch.equal(out, last)  # the int8 stream equals the int8 batch forward exactly, as the float one does


def test_calibration_round_trips_bit_identically(encoder, tmp_path: Path):
    q = QuantizedBEVEncoder(encoder)
    q.calibrate(windows(encoder, 3, seed=11))
    state = q.calibration_state()
    q.freeze()
    ckpt = tmp_path / "bev"
    ckpt.mkdir()
    write_encoder_checkpoint(ckpt, encoder, PretextHeads(encoder.cfg.bev_channels), {})
    (ckpt / "manifest.json").write_text("{}")  # read_encoder_json wants a finished output (unlisted files unverified)
    save_calibration(ckpt, state, {"target_frames": "3"})
    again = load_int8_encoder(ckpt, encoder)
    x = windows(encoder, 1, seed=12)[0]
    loaded = load_frozen_encoder(ckpt, "int8")  # what the students load
    assert isinstance(loaded, QuantizedBEVEncoder) and not any(p.requires_grad for p in loaded.parameters())
    with torch.no_grad():
        assert torch.equal(again(*x), q(*x)) and torch.equal(loaded(*x), q(*x))


def test_same_frames_give_the_same_calibration(encoder):
    a, b = QuantizedBEVEncoder(encoder), QuantizedBEVEncoder(encoder)
    a.calibrate(windows(encoder, 2, seed=13))
    b.calibrate(windows(encoder, 2, seed=13))
    sa, sb = a.calibration_state(), b.calibration_state()
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_missing_or_mismatched_calibration_is_named(encoder, tmp_path: Path):
    ckpt = tmp_path / "bev"
    ckpt.mkdir()
    with pytest.raises(InputMissingError, match=CALIBRATION_FILE):
        load_int8_encoder(ckpt, encoder)
    q = QuantizedBEVEncoder(encoder)
    q.calibrate(windows(encoder, 1, seed=14))
    state = q.calibration_state()
    other = BEVEncoder(tiny_config(fuse_pool=encoder.cfg.fuse_pool, history_frames=2), cameras()).eval()
    save_calibration(ckpt, state, {})
    with pytest.raises(CorruptArtifactError, match="does not match this encoder's architecture"):
        load_int8_encoder(ckpt, other)
    broken = tmp_path / "broken"
    shutil.copytree(ckpt, broken)
    save_tensors({k: v for k, v in list(state.items())[1:]}, broken / CALIBRATION_FILE)
    with pytest.raises(CorruptArtifactError, match=str(broken / CALIBRATION_FILE)):
        load_int8_encoder(broken, encoder)


def test_an_int8_version_that_loses_the_maps_is_refused_by_name(encoder, tmp_path: Path):
    ckpt = tmp_path / "bev"
    ckpt.mkdir()
    q = QuantizedBEVEncoder(encoder)
    q.calibrate(windows(encoder, 1, seed=15))
    save_calibration(ckpt, q.calibration_state(), {})
    final = {"loss": 0.3, "iou_static": 0.926, "iou_ped_t": 0.49, "iou_ped_t+1.0s": 0.006}
    good = {"iou_static": 0.921, "iou_ped_t": 0.489, "iou_ped_t+1.0s": 0.0}
    bad = {**good, "iou_static": 0.718}
    assert int8_iou_losses({"final": final, "int8": good}) == {}
    assert int8_iou_losses({"final": final, "int8": bad}) == {"iou_static": (0.926, 0.718)}
    assert int8_iou_losses({"final": final, "int8": None}) == {}  # no int8 version scored: nothing to judge
    (ckpt / METRICS_JSON).write_text(json.dumps({"final": final, "int8": good}))
    assert isinstance(load_int8_encoder(ckpt, encoder), QuantizedBEVEncoder)
    (ckpt / METRICS_JSON).write_text(json.dumps({"final": final, "int8": bad}))
    with pytest.raises(ConfigError, match=r"metrics.json: int8.iou_static 0.718 against final.iou_static 0.926"):
        load_int8_encoder(ckpt, encoder)
    (ckpt / METRICS_JSON).write_text("{not json")
    with pytest.raises(CorruptArtifactError, match=str(ckpt / METRICS_JSON)):
        load_int8_encoder(ckpt, encoder)


def test_precision_values_are_checked(monkeypatch):
    assert check_precision("int8", "train.encoder_precision") == "int8"
    with pytest.raises(ConfigError, match="train.encoder_precision: expected one of \\['auto', 'fp32', 'bf16', 'int8'\\], "
                                          "got 'fp16'"):
        check_precision("fp16", "train.encoder_precision")
    # given the device the encoder runs on: int8 on a CPU only, bf16 only where bfloat16 is native
    assert check_precision("int8", "eval.encoder_precision", "cpu") == "int8"
    with pytest.raises(ConfigError, match="eval.encoder_precision: int8 runs on the CPU only, got device cuda"):
        check_precision("int8", "eval.encoder_precision", "cuda")
    monkeypatch.setattr(quantize, "native_bf16", lambda device: False)
    with pytest.raises(ConfigError, match="eval.encoder_precision: expected fp32, int8 or auto on cpu, got 'bf16'"):
        check_precision("bf16", "eval.encoder_precision", "cpu")
    assert check_precision("bf16", "eval.encoder_precision") == "bf16"  # no device named: the value alone
    assert resolve_encoder_precision("auto", "eval.encoder_precision", "cpu") == "fp32"  # auto: fp32 without it
    monkeypatch.setattr(quantize, "native_bf16", lambda device: True)
    assert check_precision("bf16", "eval.encoder_precision", "cpu") == "bf16"
    assert resolve_encoder_precision("auto", "eval.encoder_precision", "cpu") == "bf16"  # ... bf16 with it
    for value in ("fp32", "int8", "bf16"):  # a concrete value is its own resolution
        assert resolve_encoder_precision(value, "eval.encoder_precision", "cpu") == value
    with pytest.raises(ConfigError, match="eval.encoder_precision: int8 runs on the CPU only"):
        resolve_encoder_precision("int8", "eval.encoder_precision", "cuda")


def test_auto_precision_loads_the_encoder_it_resolves_to(encoder, tmp_path: Path, monkeypatch):
    ckpt = tmp_path / "bev"
    ckpt.mkdir()
    write_encoder_checkpoint(ckpt, encoder, PretextHeads(encoder.cfg.bev_channels), {})
    (ckpt / "manifest.json").write_text("{}")  # a finished output (unlisted files unverified)
    monkeypatch.setattr(quantize, "native_bf16", lambda device: False)
    assert type(load_frozen_encoder(ckpt, "auto")) is BEVEncoder
    monkeypatch.setattr(quantize, "native_bf16", lambda device: True)
    assert isinstance(load_frozen_encoder(ckpt, "auto"), BF16BEVEncoder)


@pytest.mark.skipif(not native_bf16("cpu"), reason="this CPU has no native bfloat16 (AVX512-BF16 or AMX)")
def test_bf16_encoder_is_close_to_float_streams_and_returns_float32(encoder, tmp_path: Path):
    b16 = BF16BEVEncoder(encoder)
    assert not b16.training and not any(p.requires_grad for p in b16.parameters())
    sd, ref = b16.state_dict(), encoder.state_dict()
    assert sd.keys() == ref.keys() and all(torch.equal(sd[k], ref[k]) for k in sd)  # the float weights, unchanged
    rgb, depth, poses = sequence(2, seed=21)
    t = encoder.frames
    with torch.no_grad():
        batch_b, batch_f = b16(rgb[:, :t], depth[:, :t], poses[:, :t]), encoder(rgb[:, :t], depth[:, :t], poses[:, :t])
        assert batch_b.dtype == torch.float32 and batch_b.shape == batch_f.shape
        assert 0 < rel_err(batch_b, batch_f) < 0.03  # bfloat16 convolutions: close, not equal
        stream = BEVStream(b16)
        for k in range(L):
            out = stream.step(rgb[:, k], depth[:, k], poses[:, k])
        last = b16(rgb[:, L - t:], depth[:, L - t:], poses[:, L - t:])
    assert out.dtype == torch.float32 and torch.allclose(out, last, atol=1e-4, rtol=1e-3)
    ckpt = tmp_path / "bev"
    ckpt.mkdir()
    write_encoder_checkpoint(ckpt, encoder, PretextHeads(encoder.cfg.bev_channels), {})
    (ckpt / "manifest.json").write_text("{}")
    loaded = load_frozen_encoder(ckpt, "bf16")  # what the students load; no calibration file needed
    assert isinstance(loaded, BF16BEVEncoder)
    with torch.no_grad():
        assert torch.equal(loaded(rgb[:, :t], depth[:, :t], poses[:, :t]), batch_b)
    sd = b16.state_dict()  # the bfloat16 parts it prepared on first use stay outside the module tree
    assert sd.keys() == ref.keys() and all(torch.equal(sd[k], ref[k]) for k in sd)
    norms = {k: [m for m in part.modules() if isinstance(m, torch.nn.BatchNorm2d)] for k, part in b16._bf16.items()}
    assert norms == {"image": [], "dense": [b16._bf16["dense"].norm]}  # folded but the one after a sum
    assert all(p.dtype == torch.bfloat16 for part in b16._bf16.values() for p in part.parameters())
    with pytest.raises(ConfigError, match="int8 runs on the CPU only"):  # checked before anything is loaded
        load_frozen_encoder(tmp_path / "missing", "int8", "cuda")


@pytest.mark.skipif(not native_bf16("cpu"), reason="this CPU has no native bfloat16 (AVX512-BF16 or AMX)")
def test_bf16_encoder_follows_new_weights_and_moves_after_first_use(encoder):
    """Its bfloat16 parts live outside the module tree: loading other weights or moving it after its first call
    rebuilds them from the float weights instead of running stale copies."""
    rgb, depth, poses = sequence(2, seed=23)
    t = encoder.frames
    b16 = BF16BEVEncoder(encoder)
    other = BEVEncoder(encoder.cfg, encoder.cameras)
    torch.manual_seed(5)
    for p in other.parameters():
        p.data.normal_(0, 0.05)
    with torch.no_grad():
        first = b16(rgb[:, :t], depth[:, :t], poses[:, :t])  # prepares the parts from `encoder`'s weights
        b16.load_state_dict(other.state_dict())
        assert torch.equal(b16(rgb[:, :t], depth[:, :t], poses[:, :t]),
                           BF16BEVEncoder(other)(rgb[:, :t], depth[:, :t], poses[:, :t]))
        assert not torch.equal(b16(rgb[:, :t], depth[:, :t], poses[:, :t]), first)
        b16.to("cpu")  # the device move a caller may do after first use (CUDA is not needed to see the rebuild)
        assert b16._bf16 == {}
        assert torch.equal(b16(rgb[:, :t], depth[:, :t], poses[:, :t]),
                           BF16BEVEncoder(other)(rgb[:, :t], depth[:, :t], poses[:, :t]))


def test_an_uncalibrated_encoder_cannot_be_converted(encoder):
    with pytest.raises(ConfigError, match="calibrate"):
        QuantizedBEVEncoder(encoder).freeze()
    with pytest.raises(ConfigError, match="at least one calibration window"):
        QuantizedBEVEncoder(encoder).calibrate([])
