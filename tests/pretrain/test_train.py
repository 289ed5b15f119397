"""The pretext training loop on the tiny exported dataset: it learns, it resumes exactly, it refuses bad state."""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.core.errors import ConfigError, CorruptArtifactError
from pretrain.data import FrameStore, load_frames
from pretrain.geometry import cameras_from_dataset, check_grid_fits_cameras
from pretrain.model import BEVEncoder, EncoderConfig, PretextHeads
from pretrain.train import (
    LOSS_REGIONS,
    FitConfig,
    evaluate,
    fit,
    load_state,
    loss_mask,
    positive_weights,
)

# coarse grid and dense lift: the 64 x 48 tiny cameras give few points per person otherwise
ENC = dict(bev_channels=16, x_bound=[0.0, 4.0, 0.2], y_bound=[-3.2, 3.2, 0.2], lift_stride_px=2)


@pytest.fixture(scope="module")
def tiny_store(tiny_dataset) -> tuple[FrameStore, np.ndarray, list]:
    cams = cameras_from_dataset(tiny_dataset.root)
    cfg = EncoderConfig(**ENC)
    fov = check_grid_fits_cameras(cfg.grid, cams)
    store = load_frames(tiny_dataset.root, cams, cfg.grid, cfg.lift_stride_px, [0.5, 1.0], progress=False)
    return store, fov, cams


def _fit_config(**kw) -> FitConfig:
    base = dict(epochs=2, clip_frames=8, clips_per_batch=2, lr=1e-2, weight_decay=0.0, warmup_frac=0.1,
                checkpoint_every_steps=1000, log_every_steps=1, seed=0, config_hash="test")
    base.update(kw)
    return FitConfig(**base)


def _models(cams, seed: int = 0) -> tuple[BEVEncoder, PretextHeads]:
    torch.manual_seed(seed)
    return BEVEncoder(EncoderConfig(**ENC), cams), PretextHeads(ENC["bev_channels"])


def test_store_matches_dataset(tiny_store, tiny_dataset) -> None:
    """Every frame is loaded, decoded images are not blank, and labels contain people and obstacles."""
    store, fov, _ = tiny_store
    assert len(store) == tiny_dataset.counts["frames"]
    assert store.rgb.std() > 5
    assert (store.depth > 0).mean() > 0.3
    assert store.labels[:, 0][:, fov].mean() > 0.05  # static
    assert store.labels[:, 1][:, fov].sum() > 0  # people now
    assert not store.valid[-1, 2:].any() and store.valid[0].all()


def test_seen_people_label_is_a_subset_of_everyone(tiny_store, tiny_dataset) -> None:
    """people_label="seen" keeps the static channel and the validity, and marks a non-empty subset of the people
    cells of the all-people label (the tiny episodes' people stand in front of the cameras); a bad value is one
    ConfigError before anything is read."""
    store, _, cams = tiny_store
    cfg = EncoderConfig(**ENC)
    seen = load_frames(tiny_dataset.root, cams, cfg.grid, cfg.lift_stride_px, [0.5, 1.0], progress=False,
                       people_label="seen")
    np.testing.assert_array_equal(seen.labels[:, 0], store.labels[:, 0])
    np.testing.assert_array_equal(seen.valid, store.valid)
    assert not (seen.labels[:, 1:] & ~store.labels[:, 1:]).any()
    assert 0 < seen.labels[:, 1].sum() <= store.labels[:, 1].sum()
    # the all-people store with the seen people's "now" label beside it (what pretrain.evaluate scores with):
    # the same rule, so the same cells as the seen label's "now" channel
    both = load_frames(tiny_dataset.root, cams, cfg.grid, cfg.lift_stride_px, [0.5, 1.0], progress=False,
                       with_seen_now=True)
    np.testing.assert_array_equal(both.labels, store.labels)
    np.testing.assert_array_equal(both.seen_now, seen.labels[:, 1])
    assert store.seen_now is None and both.nbytes == store.nbytes + both.seen_now.nbytes
    with pytest.raises(ConfigError, match="people_label"):
        load_frames(tiny_dataset.root, cams, cfg.grid, cfg.lift_stride_px, [0.5, 1.0], progress=False,
                    people_label="visible")


@pytest.mark.slow
def test_tiny_overfit_reaches_high_iou(tiny_store, tmp_path: Path) -> None:
    """40 steps on one episode (with people in view) take it from chance to a high IoU on that episode."""
    torch.set_num_threads(2)
    store, fov, cams = tiny_store
    sl = [store.episode_slices[1]]
    enc, heads = _models(cams)
    pw = positive_weights(store, sl, fov)
    before = evaluate(enc, heads, store, sl, fov, pw, 8, 3)
    res = fit(enc, heads, store, sl, sl, fov, _fit_config(epochs=40, clips_per_batch=4), tmp_path, resume=False,
              progress=False)
    after = res["history"][-1]
    assert res["step"] == 40
    assert after["iou_static"] >= 0.8, after
    assert after["iou_ped_t"] >= 0.5, after
    assert after["iou_ped_t"] > 3 * before["iou_ped_t"], (before, after)
    assert after["val_loss"] < 0.5 * before["val_loss"]


def test_grid_loss_reads_the_labels_outside_the_view(tiny_store, tmp_path: Path) -> None:
    """``loss_region="grid"`` trains on the cells outside the cameras' view too: from the same start and batches,
    changing only the labels outside the view changes what two steps of the grid loss learn and leaves the
    field-of-view loss's weights bit-identical; an unknown region is one named error."""
    torch.set_num_threads(2)
    store, fov, cams = tiny_store
    assert not fov.all()
    sl = [store.episode_slices[1]]
    flipped = replace(store, labels=np.where(fov[None, None], store.labels, 1 - store.labels).astype(store.labels.dtype))
    for region in LOSS_REGIONS:
        weights = []
        for k, st in enumerate((store, flipped)):
            enc, heads = _models(cams)
            fit(enc, heads, st, sl, sl, fov, _fit_config(epochs=1, loss_region=region), tmp_path / f"{region}{k}",
                resume=False, progress=False, stop_at_step=2)
            weights.append(_weights(heads))
        same = all(torch.equal(weights[0][n], weights[1][n]) for n in weights[0])
        assert same == (region == "fov"), region
    assert loss_mask(fov, "grid").all() and (loss_mask(fov, "fov") == fov).all()
    with pytest.raises(ConfigError, match="pretrain.loss_region"):
        loss_mask(fov, "world")


def test_bf16_training_keeps_the_geometry_and_weights_in_float32_and_learns(tiny_store, tmp_path: Path) -> None:
    """``precision="bf16"`` (``pretrain.precision``): under the autocast the encoder hands float32 to its geometry
    (lift, warp) and returns a float32 ``s_bev`` close to the float32 forward's; 24 steps lower the validation loss
    about as far as float32 does (0.91 → 0.41 both); the trained weights stay float32."""
    from pipeline.core.device import autocast, native_bf16

    if not native_bf16("cpu"):
        pytest.skip("this CPU has no native bfloat16")
    torch.set_num_threads(2)
    store, fov, cams = tiny_store
    sl = [store.episode_slices[1]]
    enc, heads = _models(cams)
    rgb = torch.from_numpy(store.rgb[sl[0][0]:sl[0][0] + enc.frames])[None]
    depth = torch.from_numpy(store.depth[sl[0][0]:sl[0][0] + enc.frames])[None]
    poses = torch.from_numpy(store.pose[sl[0][0]:sl[0][0] + enc.frames])[None]
    with torch.no_grad():
        ref = enc.fuse(enc.encode_frames(rgb[0], depth[0])[None], poses)
        with autocast("cpu", "bf16"):
            maps = enc.encode_frames(rgb[0], depth[0])
            got = enc.fuse(maps[None], poses)
    assert maps.dtype == torch.float32 and got.dtype == torch.float32
    assert (got - ref).abs().mean() < 0.05 * ref.abs().mean()
    pw = positive_weights(store, sl, fov)
    losses = {}
    for precision in ("fp32", "bf16"):
        enc, heads = _models(cams)
        before = evaluate(enc, heads, store, sl, fov, pw, 8, 3)["val_loss"]
        res = fit(enc, heads, store, sl, sl, fov, _fit_config(epochs=24, clips_per_batch=4, lr=3e-3,
                                                              precision=precision),
                  tmp_path / precision, resume=False, progress=False)
        losses[precision] = res["history"][-1]["val_loss"]
        assert all(t.dtype == torch.float32 for t in [*enc.state_dict().values(), *heads.state_dict().values()]
                   if t.is_floating_point())
    assert losses["bf16"] < 0.6 * before and losses["bf16"] == pytest.approx(losses["fp32"], rel=0.1), losses


def _weights(m: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in m.state_dict().items()}


def test_resume_continues_from_saved_step(tiny_store, tmp_path: Path) -> None:
    """Stopped after 3 steps and resumed, training ends with the weights of an uninterrupted run; the log has
    every step once."""
    store, fov, cams = tiny_store
    sl = store.episode_slices
    fc = _fit_config(epochs=2)
    enc_a, heads_a = _models(cams)
    full = fit(enc_a, heads_a, store, sl[:1], sl[1:], fov, fc, tmp_path / "a", resume=False, progress=False)

    enc_b, heads_b = _models(cams)
    part = fit(enc_b, heads_b, store, sl[:1], sl[1:], fov, fc, tmp_path / "b", resume=False, progress=False,
               stop_at_step=3)
    assert part["stopped"] and part["step"] == 3
    assert load_state(tmp_path / "b" / "state" / "last.pt")["step"] == 3
    enc_c, heads_c = _models(cams, seed=123)  # a fresh process would start from other weights
    rest = fit(enc_c, heads_c, store, sl[:1], sl[1:], fov, fc, tmp_path / "b", resume=True, progress=False)
    assert rest["step"] == full["step"]
    for name, v in _weights(enc_a).items():
        torch.testing.assert_close(enc_c.state_dict()[name], v, rtol=1e-4, atol=1e-5, msg=name)
    with open(tmp_path / "b" / "train_log.csv", newline="") as f:
        steps = [int(r["step"]) for r in csv.DictReader(f)]
    assert steps == list(range(1, full["step"] + 1))
    assert [h["iou_static"] for h in rest["history"]] == pytest.approx([h["iou_static"] for h in full["history"]],
                                                                       abs=1e-3)


def test_resume_refuses_other_config_and_corrupt_state(tiny_store, tmp_path: Path) -> None:
    store, fov, cams = tiny_store
    sl = store.episode_slices
    enc, heads = _models(cams)
    fit(enc, heads, store, sl[:1], sl[1:], fov, _fit_config(epochs=1), tmp_path, resume=False, progress=False,
        stop_at_step=1)
    with pytest.raises(ConfigError, match="another config"):
        fit(enc, heads, store, sl[:1], sl[1:], fov, _fit_config(epochs=1, config_hash="other"), tmp_path,
            resume=True, progress=False)
    state = tmp_path / "state" / "last.pt"
    state.write_bytes(state.read_bytes()[: state.stat().st_size // 2])
    with pytest.raises(CorruptArtifactError, match=str(state)):
        fit(enc, heads, store, sl[:1], sl[1:], fov, _fit_config(epochs=1), tmp_path, resume=True, progress=False)


def _tensors(obj) -> list[torch.Tensor]:
    if isinstance(obj, torch.Tensor):
        return [obj]
    if isinstance(obj, dict):
        return [t for v in obj.values() for t in _tensors(v)]
    if isinstance(obj, list | tuple):
        return [t for v in obj for t in _tensors(v)]
    return []


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_fit_on_cuda_saves_a_device_free_state_that_resumes_on_cpu(tiny_store, tmp_path: Path) -> None:
    """Two steps on the GPU: the first loss matches the CPU's, the saved state holds only CPU tensors (it loads
    without ``map_location``), and the CPU finishes the run from it; the encoder checkpoint loads on the CPU."""
    from safetensors.torch import load_file

    from pretrain.checkpoint import write_encoder_checkpoint

    store, fov, cams = tiny_store
    sl = store.episode_slices
    fc = _fit_config(epochs=2)  # 2 steps per epoch on the tiny episode
    enc, heads = _models(cams)
    fit(enc, heads, store, sl[:1], sl[1:], fov, fc, tmp_path / "cpu", resume=False, progress=False, stop_at_step=2)
    enc, heads = _models(cams)
    enc.cuda()
    heads.cuda()
    part = fit(enc, heads, store, sl[:1], sl[1:], fov, fc, tmp_path / "gpu", resume=False, progress=False,
               stop_at_step=2)
    assert part["step"] == 2 and all(p.is_cuda for p in enc.parameters())
    state = torch.load(tmp_path / "gpu" / "state" / "last.pt", weights_only=True)  # no map_location on purpose
    assert {t.device.type for t in _tensors(state)} == {"cpu"}

    def first_loss(run: str) -> float:
        with open(tmp_path / run / "train_log.csv", newline="") as f:
            return float(next(csv.DictReader(f))["loss"])

    assert first_loss("gpu") == pytest.approx(first_loss("cpu"), rel=1e-2)
    history = evaluate(enc, heads, store, sl[1:], fov, torch.tensor(part["pos_weight"]), 8, 2)
    assert np.isfinite(history["val_loss"])

    write_encoder_checkpoint(tmp_path / "gpu", enc, heads, {})
    assert {t.device.type for t in load_file(str(tmp_path / "gpu" / "encoder.safetensors")).values()} == {"cpu"}

    enc_c, heads_c = _models(cams, seed=123)  # resumed on the CPU
    rest = fit(enc_c, heads_c, store, sl[:1], sl[1:], fov, fc, tmp_path / "gpu", resume=True, progress=False)
    assert rest["step"] == 4 and not rest["stopped"] and np.isfinite(rest["history"][-1]["val_loss"])
