"""Tests of pretrain.model: the causal time convolution, batch vs streaming encoder, stream resets, shapes and
config validation (tiny 64 x 48 cameras, an 8-channel 20 x 32 grid, eval mode). The encoder's tests run for
``fuse_pool`` 1 and 2 (temporal model and decoder on the full or the 2 x 2 pooled grid)."""

from __future__ import annotations

import copy
import math

import pytest
import torch
import torch.nn.functional as F

from pipeline.core.errors import ConfigError
from pretrain.geometry import Camera
from pretrain.model import TARGETS, BEVEncoder, BEVStream, EncoderConfig, PretextHeads, TimeConv
from sim.cameras import CameraSpec

W, H = 64, 48
L = 6  # frames in the test sequences
pytestmark = pytest.mark.usefixtures("one_thread")  # conftest; so is the `encoder` fixture


def cameras() -> list[Camera]:
    specs = (CameraSpec("left", W, H, 70.0, 35.0, 0.0, (0.1, 0.03, 0.8)),
             CameraSpec("right", W, H, 70.0, -35.0, 0.0, (0.1, -0.03, 0.8)))
    return [Camera.from_dict(s.to_dict()) for s in specs]


def tiny_config(**kw) -> EncoderConfig:
    return EncoderConfig(**({"bev_channels": 8, "x_bound": [0.0, 4.0, 0.2], "y_bound": [-3.2, 3.2, 0.2],
                             "history_frames": 3} | kw))


def randomise_norms(module: torch.nn.Module, gen: torch.Generator) -> None:
    """Non-trivial BatchNorm statistics and affine parameters (eval mode then does more than the identity)."""
    for m in module.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            c = m.num_features
            m.running_mean.copy_(0.1 * torch.randn(c, generator=gen))
            m.running_var.copy_(0.5 + torch.rand(c, generator=gen))
            m.weight.data.copy_(0.5 + torch.rand(c, generator=gen))
            m.bias.data.copy_(0.1 * torch.randn(c, generator=gen))


def sequence(b: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``b`` sequences of L frames: uint8 images, depth in [0.5, 6] m, smooth float64 poses (a gentle arc)."""
    g = torch.Generator().manual_seed(seed)
    rgb = torch.randint(0, 256, (b, L, 2, 3, H, W), dtype=torch.uint8, generator=g)
    depth = 0.5 + 5.5 * torch.rand(b, L, 2, H, W, generator=g)
    t = torch.arange(L, dtype=torch.float64)
    poses = torch.zeros(b, L, 3, dtype=torch.float64)
    for i in range(b):
        x0, y0, yaw0 = 1.0 + i, -2.0 + 0.5 * i, 0.3 - 0.4 * i
        yaw = yaw0 + 0.12 * t  # turning left, 0.25 m per frame
        poses[i, :, 2] = yaw
        poses[i, :, 0] = x0 + torch.cumsum(0.25 * torch.cos(yaw), 0)
        poses[i, :, 1] = y0 + torch.cumsum(0.25 * torch.sin(yaw), 0)
    return rgb, depth, poses


def window_index(k: int, frames: int, start: int = 0) -> list[int]:
    """Frames of the window ending at k; history before ``start`` repeats frame ``start`` (the documented rule)."""
    return [max(j, start) for j in range(k - frames + 1, k + 1)]


def batch_window(enc: BEVEncoder, rgb, depth, poses, k: int, start: int = 0) -> torch.Tensor:
    idx = window_index(k, enc.frames, start)
    with torch.no_grad():
        return enc(rgb[:, idx], depth[:, idx], poses[:, idx])


# ---------------------------------------------------------------- TimeConv


@pytest.mark.parametrize("t", [2, 3, 5])
def test_timeconv_equals_conv3d(t):
    """TimeConv (pairs of frames through one conv2d) equals F.conv3d with the same weight, padding (0, 1, 1)."""
    torch.manual_seed(0)
    conv = TimeConv(4, 6).double()
    x = torch.randn(2, 4, t, 7, 9, dtype=torch.float64)
    y = conv(x)
    ref = F.conv3d(x, conv.weight, padding=(0, 1, 1))
    assert y.shape == ref.shape == (2, 6, t - 1, 7, 9)
    torch.testing.assert_close(y, ref, rtol=1e-10, atol=1e-10)


def test_timeconv_is_causal_in_time():
    """Output step j depends only on input frames j and j + 1."""
    torch.manual_seed(0)
    conv = TimeConv(3, 3).double()
    x = torch.randn(1, 3, 4, 5, 5, dtype=torch.float64)
    x2 = x.clone()
    x2[:, :, 3] += 1.0
    y, y2 = conv(x), conv(x2)
    torch.testing.assert_close(y[:, :, :2], y2[:, :, :2])
    assert not torch.allclose(y[:, :, 2], y2[:, :, 2])


# ---------------------------------------------------------------- batch vs streaming


def test_streaming_equals_batch(encoder):
    """BEVStream.step at every step k equals BEVEncoder.forward on the window [k-2, k-1, k] (frame 0 repeated
    for the missing history), for a moving robot."""
    rgb, depth, poses = sequence(1, seed=0)
    stream = BEVStream(encoder)
    outs = []
    for k in range(L):
        out = stream.step(rgb[:, k], depth[:, k], poses[:, k])
        ref = batch_window(encoder, rgb, depth, poses, k)
        assert out.shape == ref.shape == (1, *encoder.out_shape)
        torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-4)
        outs.append(out)
    # the outputs are not trivial and the history matters: a window of the newest frame alone differs
    assert outs[-1].abs().sum() > 0
    k = L - 1
    alone = batch_window(encoder, rgb, depth, poses, k, start=k)
    assert (alone - outs[-1]).abs().max() > 1e-2


def test_image_trunk_runs_channels_last_with_the_nchw_result(encoder):
    """In eval mode image_features feeds the trunk channels-last (faster on the CPU) and returns contiguous features
    equal to the NCHW trunk's (pretrain.bench.NCHWTrunkEncoder, same weights); training mode keeps NCHW."""
    from pretrain.bench import NCHWTrunkEncoder

    ref = NCHWTrunkEncoder(encoder.cfg, encoder.cameras).eval()
    ref.load_state_dict(encoder.state_dict())
    seen = []
    hook = encoder.trunk[0].register_forward_pre_hook(lambda m, a: seen.append(a[0].is_contiguous(
        memory_format=torch.channels_last)))
    rgb = sequence(1, seed=3)[0][0, 0]
    try:
        with torch.no_grad():
            out = encoder.image_features(rgb)
            expected = ref.image_features(rgb)
    finally:
        hook.remove()
    assert seen == [True] and out.is_contiguous()
    assert out.abs().sum() > 0
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=1e-5)
    seen.clear()
    training = copy.deepcopy(encoder).train()  # a copy: training mode moves the shared fixture's BatchNorm statistics
    training.trunk[0].register_forward_pre_hook(lambda m, a: seen.append(a[0].is_contiguous()))
    with torch.no_grad():
        training.image_features(rgb)
    assert seen == [True]  # NCHW-contiguous in training


def test_streaming_equals_batch_for_a_batch_of_streams(encoder):
    """B = 2 independent streams in one step call give the same as the batch forward of each window."""
    rgb, depth, poses = sequence(2, seed=1)
    stream = BEVStream(encoder)
    for k in range(4):
        out = stream.step(rgb[:, k], depth[:, k], poses[:, k])
        torch.testing.assert_close(out, batch_window(encoder, rgb, depth, poses, k), rtol=1e-4, atol=1e-4)


def test_stream_first_resets_only_the_flagged_stream(encoder):
    """first = [True, False] at step 3 restarts stream 0 (its history becomes frame 3 repeated) and leaves
    stream 1 alone; each equals a single-stream run of its own."""
    rgb, depth, poses = sequence(2, seed=2)
    reset_at = 3
    both = BEVStream(encoder)
    got = []
    for k in range(L):
        first = torch.tensor([True, False]) if k == reset_at else None
        got.append(both.step(rgb[:, k], depth[:, k], poses[:, k], first=first))
    for i in range(2):
        single = BEVStream(encoder)
        for k in range(L):
            first = torch.tensor([True]) if (i == 0 and k == reset_at) else None
            out = single.step(rgb[i:i + 1, k], depth[i:i + 1, k], poses[i:i + 1, k], first=first)
            torch.testing.assert_close(got[k][i:i + 1], out, rtol=1e-4, atol=1e-4)
    # and the reset matches the batch rule: stream 0 after the reset = windows starting at reset_at
    for k in range(reset_at, L):
        ref = batch_window(encoder, rgb[:1], depth[:1], poses[:1], k, start=reset_at)
        torch.testing.assert_close(got[k][:1], ref, rtol=1e-4, atol=1e-4)
    # stream 1 kept its history: it equals the un-reset batch window, which differs from a reset one
    k = reset_at
    torch.testing.assert_close(got[k][1:], batch_window(encoder, rgb[1:], depth[1:], poses[1:], k),
                               rtol=1e-4, atol=1e-4)
    reset_1 = batch_window(encoder, rgb[1:], depth[1:], poses[1:], k, start=k)
    assert (reset_1 - got[k][1:]).abs().max() > 1e-2


def test_stream_reset_forgets_history(encoder):
    """After reset() the next step behaves like the first frame of an episode."""
    rgb, depth, poses = sequence(1, seed=3)
    stream = BEVStream(encoder)
    for k in range(3):
        stream.step(rgb[:, k], depth[:, k], poses[:, k])
    stream.reset()
    out = stream.step(rgb[:, 3], depth[:, 3], poses[:, 3])
    torch.testing.assert_close(out, batch_window(encoder, rgb, depth, poses, 3, start=3), rtol=1e-4, atol=1e-4)


def test_stream_batch_size_change_starts_new_episodes(encoder):
    """When the number of streams changes, the old history is dropped: the step equals a fresh start."""
    rgb, depth, poses = sequence(2, seed=7)
    stream = BEVStream(encoder)
    for k in range(3):
        stream.step(rgb[:, k], depth[:, k], poses[:, k])
    out = stream.step(rgb[:1, 3], depth[:1, 3], poses[:1, 3])
    ref = batch_window(encoder, rgb[:1], depth[:1], poses[:1], 3, start=3)
    torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-4)


def test_encoder_depends_only_on_relative_poses(encoder):
    """Only relative poses matter: shifting and rotating every pose of a window by one rigid motion leaves
    s_bev unchanged."""
    rgb, depth, poses = sequence(1, seed=4)
    idx = [1, 2, 3]
    moved = poses.clone()
    a = 1.1
    c, s = math.cos(a), math.sin(a)
    moved[..., 0] = 5.0 + c * poses[..., 0] - s * poses[..., 1]
    moved[..., 1] = -2.0 + s * poses[..., 0] + c * poses[..., 1]
    moved[..., 2] = poses[..., 2] + a
    with torch.no_grad():
        y0 = encoder(rgb[:, idx], depth[:, idx], poses[:, idx])
        y1 = encoder(rgb[:, idx], depth[:, idx], moved[:, idx])
    torch.testing.assert_close(y0, y1, rtol=1e-4, atol=1e-4)


# ---------------------------------------------------------------- shapes and config


def test_out_shape_matches_output(encoder):
    """out_shape is (C, X, Y) of the actual s_bev, and describe() reports it."""
    rgb, depth, poses = sequence(2, seed=5)
    with torch.no_grad():
        y = encoder(rgb[:, :3], depth[:, :3], poses[:, :3])
    assert encoder.out_shape == (8, 20, 32)
    assert tuple(y.shape) == (2, *encoder.out_shape)
    assert encoder.describe()["s_bev_shape"] == [8, 20, 32]


def test_forward_rejects_a_wrong_window_length(encoder):
    rgb, depth, poses = sequence(1, seed=6)
    with pytest.raises(ValueError):
        encoder(rgb[:, :2], depth[:, :2], poses[:, :2])


@pytest.mark.parametrize("kw", [{"resnet_stages": 5}, {"resnet_stages": 0}, {"bev_channels": 0},
                                {"lift_stride_px": 0}, {"history_frames": 0}, {"bev_channels": 8.5},
                                {"x_bound": [0.0, 4.05, 0.2]}, {"fuse_pool": 0}, {"fuse_pool": 3},
                                {"fuse_pool": True}])
def test_encoder_config_validate_rejects(kw):
    """EncoderConfig.validate raises ConfigError for out-of-range architecture values and bad grids."""
    with pytest.raises(ConfigError):
        tiny_config(**kw).validate()


def test_encoder_config_default_is_valid():
    EncoderConfig().validate()
    tiny_config().validate()


def test_fuse_pool_error_names_the_grid():
    """A pool that does not divide the grid is named with the grid's sizes."""
    with pytest.raises(ConfigError, match=r"^encoder\.fuse_pool: expected a divisor of both BEV grid sizes \[20, 32\], "
                                          r"got 3$"):
        tiny_config(fuse_pool=3).validate()


def test_fuse_pool_runs_the_temporal_model_on_the_pooled_grid_and_keeps_full_resolution():
    """With fuse_pool 2 the temporal model sees 10 x 16 maps, s_bev is 20 x 32 again, and the newest frame's
    full-resolution map reaches it through the refinement (a change confined to one fine cell of it changes s_bev
    most within that cell's 3 x 3 neighbourhood, the refinement's kernel)."""
    torch.manual_seed(0)
    enc = BEVEncoder(tiny_config(fuse_pool=2), cameras()).eval()
    assert enc.fuse_grid.shape == (10, 16) and enc.grid.shape == (20, 32)
    seen = []
    hook = enc.temporal.register_forward_hook(lambda m, a, y: seen.append(tuple(a[0].shape)))
    maps = torch.randn(1, 3, 8, 20, 32)
    poses = torch.zeros(1, 3, 3, dtype=torch.float64)
    with torch.no_grad():
        y0 = enc.fuse(maps, poses)
        bumped = maps.clone()
        bumped[0, -1, :, 7, 11] += 5.0
        y1 = enc.fuse(bumped, poses)
    hook.remove()
    assert seen[0] == (1, 3, 8, 10, 16) and tuple(y0.shape) == (1, 8, 20, 32)
    change = (y1 - y0).abs().sum(1)[0]
    i, j = divmod(int(change.argmax()), 32)
    assert abs(i - 7) <= 1 and abs(j - 11) <= 1


def test_pretext_heads_shape():
    """PretextHeads maps B x C x X x Y to B x 4 x X x Y (one channel per pretext target)."""
    torch.manual_seed(0)
    heads = PretextHeads(8).eval()
    y = heads(torch.randn(3, 8, 20, 32))
    assert len(TARGETS) == 4
    assert tuple(y.shape) == (3, len(TARGETS), 20, 32)
    assert torch.isfinite(y).all() and y.std() > 0
