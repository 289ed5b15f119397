"""Benchmark figures of the BEV encoder and the intention model (called by ``icrowdnav bench``; single CPU thread,
the profile's cameras).

* ``bev_lift_ms`` / ``bev_lift_reference_ms`` / ``bev_lift_speedup_vs_reference`` — :func:`lift_splat` vs the
  per-point loop :func:`lift_splat_reference` on the same rendered RGB-D frame pair (real depth from the sim, so
  the number of lifted points is realistic); the outputs are compared first;
* ``bev_stream_ms_per_step`` — :meth:`BEVStream.step`: encode the newest frame pair, warp the cached history,
  temporal model; ``bev_recompute_ms_per_step`` — :meth:`BEVEncoder.forward` on the whole window of T frames (what
  a policy without the cache would do each step); ``bev_stream_speedup_vs_recompute`` their ratio;
* ``bev_stream_hz`` — streaming steps per second; ``bev_backbone_ms`` — the image backbone alone on one frame pair.
* ``bev_stream_ms_per_step_fuse_pool2`` / ``bev_stream_speedup_fuse_pool2`` — the same streaming step with the
  temporal model and decoder on the 2 x 2 pooled grid (``encoder.fuse_pool: 2``), timed in alternation with the
  profile's encoder on the same frames (only when the profile's encoder fuses at full resolution).
* ``bev_stream_ms_per_step_nchw_trunk`` / ``bev_stream_speedup_channels_last`` — the streaming step with the image
  trunk on NCHW tensors (:class:`NCHWTrunkEncoder`, the layout before the trunk ran channels-last), timed in
  alternation with the profile's encoder on the same frames and weights, outputs compared first;
  ``trunk_train_ms_nchw`` / ``trunk_train_ms_channels_last`` / ``trunk_train_speedup_channels_last`` — forward +
  backward of the trunk and neck on a pretraining batch's images (``clips_per_batch`` x ``clip_frames`` frames of
  every camera), every thread, alternating: the layout's gain that training does not take (it keeps NCHW,
  docs/notes/2026-12-channels-last-trunk.md).
* ``pretrain_step_ms_<device>`` — one optimisation step of :func:`pretrain.train.fit` (forward, masked BCE,
  backward, AdamW; the profile's ``clips_per_batch`` x ``clip_frames``) on a synthetic frame store of the cameras'
  size, every thread the machine has, median of the steps after the first two (:func:`measure_fit_step`); with a
  GPU, ``pretrain_step_speedup_cuda_vs_cpu`` from the same run. ``python -m pretrain.bench --dataset ROOT --devices
  cpu,cuda`` measures it alone (it reads only ``ROOT/meta/info.json``: the cameras), e.g. on a GPU machine.
* ``intention_fit_s_<device>`` — the intention stage's saved model fitted on a dataset's samples
  (:func:`measure_intention_fit`; ``--intention-samples``), with its validation error per device.

The encoder has the profile's ``pretrain.encoder`` architecture with random weights (speed does not depend on
the weights); the frames come from the bench scene rendered at the profile's camera resolution.
"""

from __future__ import annotations

import copy
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.core.config import load_config
from pipeline.core.device import machine_facts, resolve_device
from pipeline.core.errors import reports_errors
from pipeline.core.timing import time_call
from pretrain.data import FrameStore
from pretrain.geometry import (
    Camera,
    cameras_from_dataset,
    check_grid_fits_cameras,
    lift_splat,
    lift_splat_reference,
)
from pretrain.intention import (
    FitOptions,
    ForecasterConfig,
    IntentionConfig,
    IntentionForecaster,
    collect,
    fit_model,
    predict,
    split_samples,
)
from pretrain.model import LEGACY_ENCODER, BEVEncoder, BEVStream, EncoderConfig, PretextHeads
from pretrain.stage import PretrainConfig
from pretrain.train import FitConfig, fit


class NCHWTrunkEncoder(BEVEncoder):
    """The reference of ``bev_stream_speedup_channels_last``: :class:`BEVEncoder` with its image trunk on NCHW
    tensors in eval mode too (the same weights and arithmetic; only the memory layout the convolutions and the
    stem's max-pool see)."""

    def image_features(self, rgb: torch.Tensor) -> torch.Tensor:
        f = self.neck(self.trunk(self.normalize(rgb))).float()
        if tuple(f.shape[-2:]) != tuple(self.geom.lift_hw):
            f = torch.nn.functional.interpolate(f, size=tuple(self.geom.lift_hw), mode="bilinear",
                                                align_corners=False)
        return f


def measure_trunk_layout(encoder: BEVEncoder, images: int, seed: int = 0, rounds: int = 3) -> dict[str, float]:
    """Forward + backward of ``encoder``'s trunk and neck on ``images`` random frames of its cameras' size, the input
    channels-last (what :meth:`BEVEncoder.image_features` does) vs NCHW, alternating ``rounds`` times (the fastest
    of two steps each), with the threads the caller set; on a copy of the trunk (``encoder`` is left untouched)."""
    c = encoder.cameras[0]
    g = torch.Generator().manual_seed(seed)
    x0 = torch.rand(images, 3, c.height, c.width, generator=g)
    net = copy.deepcopy(torch.nn.Sequential(encoder.trunk, encoder.neck)).train()  # the caller's stays as it is
    times: dict[str, list[float]] = {"nchw": [], "channels_last": []}

    def step(x: torch.Tensor) -> float:
        t = time.perf_counter()
        net(x).sum().backward()
        return time.perf_counter() - t

    for _ in range(rounds):
        for layout, x in (("nchw", x0), ("channels_last", x0.contiguous(memory_format=torch.channels_last))):
            times[layout].append(min(step(x), step(x)))
    out = {f"trunk_train_ms_{k}": 1000.0 * float(np.median(v)) for k, v in times.items()}
    out["trunk_train_speedup_channels_last"] = out["trunk_train_ms_nchw"] / out["trunk_train_ms_channels_last"]
    return out


def _ms(fn, seconds: float) -> float:
    """Mean milliseconds per call (the bench's own timer, :func:`pipeline.core.timing.time_call`)."""

    return 1000.0 * time_call(fn, seconds)


def measure_bev(sim_cfg: Any, scene: str, density: float, seed: int, encoder_cfg: Any, seconds: float) -> dict:
    """The figures of this module (see its docstring)."""
    import gymnasium as gym

    import sim  # noqa: F401  # lazy: registers the env; the fit-step bench runs on GPU machines without the sim

    env = gym.make("icrowdnav/CrowdNav-v0", config=replace(sim_cfg, scene=scene, density=density, obs_mode="visual",
                                                           info_level="basic"))
    obs, _ = env.reset(seed=seed)
    u = env.unwrapped
    cameras = [Camera.from_dict(spec.to_dict()) for spec in u.cameras]
    frames = []
    for _ in range(encoder_cfg.history_frames + 1):
        frames.append(obs)
        obs, *_ = env.step(np.array([0.6, 0.2], dtype=np.float32))
    env.close()
    names = [c.name for c in cameras]

    def tensors(o):
        rgb = torch.from_numpy(np.stack([o[f"rgb_{n}"] for n in names])).permute(0, 3, 1, 2).unsqueeze(0)
        depth = torch.from_numpy(np.stack([o[f"depth_{n}"] for n in names])).unsqueeze(0)
        return rgb.contiguous(), depth, torch.from_numpy(o["odom"].astype(np.float64)).unsqueeze(0)

    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    out: dict[str, float] = {}
    try:
        torch.manual_seed(seed)
        enc = BEVEncoder(encoder_cfg, cameras).eval()
        rgb, depth, pose = tensors(frames[-1])
        with torch.inference_mode():
            feats = enc.image_features(rgb[0]).unsqueeze(0)
            d = enc.lift_depth(depth)
            fast = lift_splat(feats, d, enc.geom, enc.grid)
            ref = lift_splat_reference(feats.double().numpy(), d.double().numpy(), cameras,
                                       encoder_cfg.lift_stride_px, enc.grid)
            if not np.allclose(fast.numpy(), ref, rtol=1e-4, atol=1e-3):
                raise RuntimeError("fast lift disagrees with the reference lift")
            out["bev_lift_points"] = float((d > 0).sum())
            out["bev_lift_ms"] = _ms(lambda: lift_splat(feats, d, enc.geom, enc.grid), seconds / 4)
            t0 = time.perf_counter()
            lift_splat_reference(feats.double().numpy(), d.double().numpy(), cameras, encoder_cfg.lift_stride_px,
                                 enc.grid)
            out["bev_lift_reference_ms"] = 1000.0 * (time.perf_counter() - t0)
            out["bev_lift_speedup_vs_reference"] = out["bev_lift_reference_ms"] / out["bev_lift_ms"]
            out["bev_backbone_ms"] = _ms(lambda: enc.image_features(rgb[0]), seconds / 4)

            window = [tensors(f) for f in frames[-encoder_cfg.history_frames:]]
            w_rgb = torch.stack([w[0] for w in window], 1)
            w_depth = torch.stack([w[1] for w in window], 1)
            w_pose = torch.stack([w[2] for w in window], 1)
            out["bev_recompute_ms_per_step"] = _ms(lambda: enc(w_rgb, w_depth, w_pose), seconds / 2)
            stream = BEVStream(enc)
            for w in window:
                s = stream.step(*w)
            batch = enc(w_rgb, w_depth, w_pose)
            if not torch.allclose(s, batch, atol=1e-4, rtol=1e-4):
                raise RuntimeError("streaming encoder disagrees with the batch forward")
            out["bev_stream_ms_per_step"] = _ms(lambda: stream.step(*window[-1]), seconds / 2)
            if encoder_cfg.fuse_pool == 1 and all(n % 2 == 0 for n in enc.grid.shape):
                pooled = BEVStream(BEVEncoder(replace(encoder_cfg, fuse_pool=2), cameras).eval())
                for w in window:
                    pooled.step(*w)
                full_ms, pooled_ms = [], []
                for _ in range(3):  # alternating: a drifting machine speed hits both alike
                    full_ms.append(_ms(lambda: stream.step(*window[-1]), seconds / 6))
                    pooled_ms.append(_ms(lambda: pooled.step(*window[-1]), seconds / 6))
                out["bev_stream_ms_per_step_fuse_pool2"] = float(np.median(pooled_ms))
                out["bev_stream_speedup_fuse_pool2"] = float(np.median(full_ms) / np.median(pooled_ms))
            ref = NCHWTrunkEncoder(encoder_cfg, cameras).eval()
            ref.load_state_dict(enc.state_dict())
            nchw = BEVStream(ref)
            for w in window:
                s_ref = nchw.step(*w)
            if not torch.allclose(s, s_ref, atol=1e-4, rtol=1e-4):
                raise RuntimeError("the NCHW-trunk reference disagrees with the channels-last encoder")
            cl_ms, nchw_ms = [], []
            for _ in range(3):  # alternating, as above
                cl_ms.append(_ms(lambda: stream.step(*window[-1]), seconds / 6))
                nchw_ms.append(_ms(lambda: nchw.step(*window[-1]), seconds / 6))
            out["bev_stream_ms_per_step_nchw_trunk"] = float(np.median(nchw_ms))
            out["bev_stream_speedup_channels_last"] = float(np.median(nchw_ms) / np.median(cl_ms))
        out["bev_stream_speedup_vs_recompute"] = out["bev_recompute_ms_per_step"] / out["bev_stream_ms_per_step"]
        out["bev_stream_hz"] = 1000.0 / out["bev_stream_ms_per_step"]
        out["bev_grid_cells"] = float(np.prod(enc.grid.shape))
        out["bev_channels"] = float(encoder_cfg.bev_channels)
    finally:
        torch.set_num_threads(prev)
    out.update(measure_trunk_layout(enc, FIT_BATCH_IMAGES_PER_CAMERA * len(cameras), seed))  # every thread
    devices = ["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"]
    out.update(measure_fit_steps(cameras, encoder_cfg, devices, steps=6))  # every thread: training's setting
    return out


FIT_BATCH_IMAGES_PER_CAMERA = 4 * 8  # measure_fit_step's default clips_per_batch x clip_frames


def measure_fit_step(cameras: list[Camera], encoder_cfg: Any, device: str, *, steps: int = 12, clips_per_batch: int = 4,
                     clip_frames: int = 8, future_targets: int = 2, seed: int = 0) -> float:
    """Median milliseconds of one :func:`pretrain.train.fit` step on ``device`` (see the module docstring).

    The frames are random (speed does not depend on their content): RGB and depth at the cameras' size, random
    pose, labels and validity; one training episode long enough for ``steps + 2`` batches, the run stopped after
    them (no validation pass).
    """
    import csv
    import tempfile


    dev = resolve_device(device, "device")
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    encoder = BEVEncoder(encoder_cfg, cameras)
    heads = PretextHeads(encoder_cfg.bev_channels)
    grid = encoder_cfg.grid
    fov = check_grid_fits_cameras(grid, cameras, "encoder")
    n_train = (steps + 3) * clips_per_batch * clip_frames + encoder.frames
    n = n_train + 2 * encoder.frames + 4
    c0, stride = cameras[0], encoder_cfg.lift_stride_px
    store = FrameStore(
        rgb=rng.integers(0, 256, (n, len(cameras), 3, c0.height, c0.width), dtype=np.uint8),
        depth=rng.uniform(0.3, 8.0, (n, len(cameras), c0.height // stride, c0.width // stride)).astype(np.float32),
        pose=np.cumsum(rng.normal(0.0, 0.05, (n, 3)), 0),
        labels=(rng.random((n, 2 + future_targets, *grid.shape)) < 0.05).astype(np.uint8),
        valid=np.ones((n, 2 + future_targets), bool), episode_start=np.zeros(n, np.int64),
        episode_end=np.full(n, n, np.int64), episodes=[0], episode_slices=[(0, n)])
    store.episode_start[n_train:], store.episode_end[:n_train] = n_train, n_train
    encoder.to(dev)
    heads.to(dev)
    fc = FitConfig(epochs=1, clip_frames=clip_frames, clips_per_batch=clips_per_batch, lr=1e-3, weight_decay=1e-4,
                   warmup_frac=0.3, checkpoint_every_steps=10_000, log_every_steps=1, seed=seed, config_hash="bench")
    with tempfile.TemporaryDirectory() as tmp:
        fit(encoder, heads, store, [(0, n_train)], [(n_train, n)], fov, fc, Path(tmp), resume=False,
            stop_at_step=steps + 2, progress=False)
        with open(Path(tmp) / "train_log.csv") as f:
            rows = list(csv.DictReader(f))
    targets = clips_per_batch * clip_frames
    return float(np.median([1000.0 * targets / float(r["frames_per_s"]) for r in rows[2:]]))


def measure_fit_steps(cameras: list[Camera], encoder_cfg: Any, devices: list[str], **kwargs: Any) -> dict[str, float]:
    """``pretrain_step_ms_<device>`` for each device (and the CUDA / CPU speed-up when both are measured); on CUDA
    also ``pretrain_peak_gib_cuda``, the most GPU memory torch allocated during the steps."""
    out: dict[str, float] = {}
    for d in devices:
        key = d.split(":")[0]
        cuda = resolve_device(d, "device").type == "cuda"
        if cuda:
            torch.cuda.reset_peak_memory_stats()
        out[f"pretrain_step_ms_{key}"] = round(measure_fit_step(cameras, encoder_cfg, d, **kwargs), 2)
        if cuda:
            out[f"pretrain_peak_gib_{key}"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
    if "pretrain_step_ms_cpu" in out and "pretrain_step_ms_cuda" in out:
        out["pretrain_step_speedup_cuda_vs_cpu"] = round(out["pretrain_step_ms_cpu"] / out["pretrain_step_ms_cuda"], 2)
    return out


def write_intention_samples(dataset: Path, out: Path) -> dict[str, int]:
    """Collects the intention stage's samples of ``dataset`` (:func:`pretrain.intention.collect`, the default
    model's horizons and history) into one ``.npz`` (a few MB: the stage's inputs without the dataset's images), so
    that :func:`measure_intention_fit` can run on a machine that holds no dataset."""
    mc = ForecasterConfig()
    samples, fps, n_eps = collect(dataset, mc.horizons_s, mc.history)
    tmp = out.with_name(out.name + ".tmp.npz")
    np.savez_compressed(tmp, fps=np.float64(fps), n_episodes=np.int64(n_eps), **samples)
    tmp.replace(out)
    return {"samples": int(len(samples["speed"])), "episodes": int(n_eps)}


def measure_intention_fit(samples_npz: Path, devices: list[str], epochs: int = 12) -> dict[str, float]:
    """Fits the intention stage's saved model (track + detected pose, the default config's batch, learning rate and
    pose dropout) on the samples of :func:`write_intention_samples` once per device, split as the stage splits
    them; ``intention_fit_s_<device>`` (wall seconds for ``epochs`` epochs), ``intention_val_fde_1s_<device>``
    (validation FDE at the last horizon: the two devices must agree to within run-to-run noise) and, with both
    devices, ``intention_fit_speedup_cuda_vs_cpu``."""
    with np.load(samples_npz) as z:
        samples = {k: z[k] for k in z.files if k not in ("fps", "n_episodes")}
        n_eps = int(z["n_episodes"])
    cfg = IntentionConfig()
    mc = cfg.model
    train, val, _, _ = split_samples(samples, cfg.val_fraction, cfg.seed, cfg.max_samples, str(samples_npz), n_eps,
                                     mc.horizons_s[-1])
    opt = FitOptions(epochs, cfg.batch, cfg.lr, cfg.pose_dropout, cfg.head_aux_weight, cfg.seed)
    out: dict[str, float] = {"intention_train_samples": len(train["speed"]), "intention_epochs": epochs}
    for d in devices:
        dev = resolve_device(d, "device")
        key = d.split(":")[0]
        model = IntentionForecaster(ForecasterConfig(**{**vars(mc), "pose": True}))
        t = time.perf_counter()
        fit_model(model, train, val, opt, dev)
        if dev.type == "cuda":
            torch.cuda.synchronize()
        out[f"intention_fit_s_{key}"] = round(time.perf_counter() - t, 2)
        last = predict(model, val, dev)[:, -1] - val["target"][:, -1]
        out[f"intention_val_fde_last_m_{key}"] = round(float(np.linalg.norm(last, axis=-1).mean()), 4)
    if "intention_fit_s_cpu" in out and "intention_fit_s_cuda" in out:
        out["intention_fit_speedup_cuda_vs_cpu"] = round(out["intention_fit_s_cpu"] / out["intention_fit_s_cuda"], 2)
    return out


@reports_errors
def main(argv: list[str] | None = None) -> int:
    """``python -m pretrain.bench --dataset ROOT [--devices cpu,cuda] [--steps 12]``: the fit-step figures as JSON.

    ``--write-intention-samples F`` collects the intention stage's samples of the dataset into ``F`` (no bench);
    ``--intention-samples F`` adds the intention model's fit on those samples per device
    (:func:`measure_intention_fit`)."""
    import argparse
    import json
    import os


    ap = argparse.ArgumentParser(prog="python -m pretrain.bench", description=main.__doc__)
    ap.add_argument("--dataset", type=Path, required=True, help="a dataset root (only meta/info.json is read)")
    ap.add_argument("--devices", default="cpu,cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--profile", help="take the encoder and the batch (clips_per_batch x clip_frames) from this "
                                      "profile's pretrain section (default: the built-in EncoderConfig, 4 x 8)")
    ap.add_argument("--clips-per-batch", type=int, help="clips per step (default: the profile's, else 4)")
    ap.add_argument("--clip-frames", type=int, help="target frames per clip (default: the profile's, else 8)")
    ap.add_argument("--legacy", action="store_true",
                    help="also time the encoder as it was before the depth evidence, the BEV decoder and T = 5 "
                         "(keys *_legacy)")
    ap.add_argument("--fuse-pool", type=int, default=0,
                    help="also time the encoder with this encoder.fuse_pool (keys *_fuse_pool<N>)")
    ap.add_argument("--write-intention-samples", type=Path, help="collect the intention samples into this .npz")
    ap.add_argument("--intention-samples", type=Path, help="also time the intention model's fit on these samples")
    ap.add_argument("--intention-epochs", type=int, default=12)
    args = ap.parse_args(argv)
    torch.set_num_threads(os.cpu_count() or 1)
    devices = args.devices.split(",")
    if args.write_intention_samples:
        print(json.dumps(write_intention_samples(args.dataset, args.write_intention_samples)))
        return 0
    cams = cameras_from_dataset(args.dataset)
    encoder, batch, head = EncoderConfig(), {"clips_per_batch": 4, "clip_frames": 8}, {}
    if args.profile:
        cfg = load_config(PretrainConfig, "pretrain", profile=args.profile)
        encoder, batch = cfg.encoder, {"clips_per_batch": cfg.clips_per_batch, "clip_frames": cfg.clip_frames}
        head = {"profile": args.profile, "bev_grid_cells": int(np.prod(encoder.grid.shape))}
    batch = {k: v if getattr(args, k) is None else getattr(args, k) for k, v in batch.items()}
    kw = {"steps": args.steps, **batch}
    pooled = replace(encoder, fuse_pool=args.fuse_pool) if args.fuse_pool else None
    if pooled is not None:
        pooled.validate()
    out = {**head, **batch, **measure_fit_steps(cams, encoder, devices, **kw)}
    if args.legacy:
        legacy = EncoderConfig(**{**LEGACY_ENCODER, "history_frames": 3})
        out.update({f"{k}_legacy": v for k, v in measure_fit_steps(cams, legacy, devices, **kw).items()})
    if pooled is not None:
        out.update({f"{k}_fuse_pool{args.fuse_pool}": v
                    for k, v in measure_fit_steps(cams, pooled, devices, **kw).items()})
    if args.intention_samples:
        out.update(measure_intention_fit(args.intention_samples, devices, args.intention_epochs))
    print(json.dumps(out | machine_facts()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
