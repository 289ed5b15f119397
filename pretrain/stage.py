"""``icrowdnav pretrain``: pretrain the spatio-temporal BEV encoder on a recorded LeRobot dataset.

::

    icrowdnav pretrain --profile default                     # make pretrain; reads DATA_DIR/datasets/icrowdnav/expert
    icrowdnav pretrain --resume                              # continue a killed run from its last saved step
    icrowdnav pretrain --epochs 1 --encoder.bev_channels 16 --name bev_small
    icrowdnav pretrain --device cuda                         # on the GPU (default auto: CUDA when present)

Input: a dataset exported by ``icrowdnav export`` (RGB videos, depth, odometry and the privileged labels
``privileged.ped_state`` / ``privileged.local_occupancy``). Output: ``DATA_DIR/checkpoints/<name>/`` (tree in
:mod:`pretrain.checkpoint`); :func:`pretrain.checkpoint.load_encoder` gives the frozen encoder to ``train``.

The output is written in place (like ``record``): a killed run keeps ``state/last.pt`` and ``--resume`` continues
it; ``manifest.json`` is written last, so consumers refuse an unfinished checkpoint.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

from pipeline.core import layout
from pipeline.core.artifacts import atomic_write_json, json_safe
from pipeline.core.config import BaseStageConfig, check_run_name, config_hash
from pipeline.core.device import device_counts, resolve_device, resolve_precision
from pipeline.core.errors import ConfigError, CorruptArtifactError
from pretrain.checkpoint import METRICS_JSON, read_weights, write_encoder_checkpoint
from pretrain.data import (
    PEOPLE_LABELS,
    Batch,
    check_dataset,
    check_grid_in_local_map,
    load_frames,
    make_batches,
    make_clips,
    split_episodes,
)
from pretrain.evaluate import CAL_THRESHOLDS, calibrate, episode_counts, turning_pedestrian_frame
from pretrain.figures import plot_curves, plot_fov, plot_sample
from pretrain.geometry import check_grid_fits_cameras
from pretrain.model import TARGETS, BEVEncoder, EncoderConfig, PretextHeads
from pretrain.quantize import INT8_MAX_IOU_DROP, QuantizedBEVEncoder, int8_iou_losses, save_calibration
from pretrain.train import LOSS_REGIONS, FitConfig, evaluate, fit, forward_batch

log = logging.getLogger("icrowdnav")


@dataclass
class PretrainConfig(BaseStageConfig):
    """Config of the ``pretrain`` stage."""
    PLACEMENT_FIELDS: ClassVar[tuple[str, ...]] = ("threads",)  # how many cores, as device says where

    repo_id: str = "icrowdnav/expert"  # dataset to train on: DATA_DIR/datasets/<repo_id>/
    name: str = "bev"  # output: DATA_DIR/checkpoints/<name>/
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    future_s: list[float] = field(default_factory=lambda: [0.5, 1.0])  # horizons of the future pedestrian targets (s)
    # whom the people targets mark: all (every person present in the grid) | seen (only the people the current
    # frame's depth reaches, now and in the future targets: a camera cannot know of the others; docs/results.md)
    people_label: str = "all"
    # the cells the training loss reads: fov (the cameras' field of view) | grid (the whole grid: beyond the view the
    # heads learn what the temporal model carries and the prior, instead of an unsupervised extrapolation, which
    # `python -m pretrain.evaluate CKPT --region outside` measures); validation IoU stays on the field of view
    loss_region: str = "fov"
    epochs: int = 3  # passes over the training episodes
    clip_frames: int = 8  # target frames per clip (each clip adds T-1 frames of context)
    clips_per_batch: int = 4  # clips per optimisation step
    lr: float = 2e-3  # AdamW peak learning rate (one-cycle schedule: warm-up, cosine decay)
    weight_decay: float = 1e-4  # AdamW weight decay
    warmup_frac: float = 0.1  # fraction of the steps spent warming up
    # BCE weight of positives = sqrt(negatives / positives), at most this: a weight w inflates the learned odds by w
    # (pedestrians: w ~ 8 at a cap of 10 put p = 0.5 far from the best threshold), so keep it small
    pos_weight_cap: float = 3.0
    val_fraction: float = 0.1  # fraction of the episodes held out for validation (split by episode)
    max_episodes: int = 0  # use at most this many episodes of the dataset (0 = all)
    checkpoint_every_steps: int = 100  # save the training state this often (and at every epoch end)
    log_every_steps: int = 10  # write a train_log.csv / TensorBoard row this often
    threads: int = 0  # torch CPU threads (0 = every core)
    # where the encoder trains: auto (CUDA when this machine has it, else the CPU) | cpu | cuda | cuda:N (--device
    # cuda); not in the config hash: a run resumes on another device, and the manifest's counts record the one used
    device: str = "auto"
    figures: int = 4  # validation samples drawn as figures
    # training frames (whole seeded clips) whose activations calibrate the encoder's int8 version, saved beside it
    # (int8_calibration.safetensors, pretrain.quantize; train.encoder_precision int8 uses it); its validation IoU
    # is in metrics.json "int8". 0 = no int8 version
    int8_calibration_frames: int = 400
    # the training's arithmetic: fp32, or bf16 (the encoder's convolutions under bfloat16 autocast; its geometry, the
    # loss, the weights and the optimiser in float32), or auto = bf16 where the device computes bfloat16 natively
    # (pipeline.core.device.resolve_precision); validation always in float32
    precision: str = "fp32"
    max_ram_gb: float = 16.0  # refuse to load more frames than this (GB, estimated before reading)
    progress: bool = True  # progress bars

    def validate(self) -> None:
        super().validate()
        check_run_name(self.name)
        for k in ("epochs", "clip_frames", "clips_per_batch", "checkpoint_every_steps", "log_every_steps"):
            if getattr(self, k) < 1:
                raise ConfigError(f"pretrain.{k}: expected an integer >= 1, got {getattr(self, k)}")
        for k in ("max_episodes", "threads", "figures", "int8_calibration_frames"):
            if getattr(self, k) < 0:
                raise ConfigError(f"pretrain.{k}: expected an integer >= 0, got {getattr(self, k)}")
        if not (math.isfinite(self.pos_weight_cap) and self.pos_weight_cap >= 1):
            raise ConfigError(f"pretrain.pos_weight_cap: expected a number >= 1, got {self.pos_weight_cap}")
        if not (self.lr > 0 and self.weight_decay >= 0 and 0 <= self.warmup_frac < 1 and self.max_ram_gb > 0):
            raise ConfigError(f"pretrain: expected lr > 0, weight_decay >= 0, 0 <= warmup_frac < 1, max_ram_gb > 0, "
                              f"got {self.lr}, {self.weight_decay}, {self.warmup_frac}, {self.max_ram_gb}")
        if not 0 < self.val_fraction < 1:
            raise ConfigError(f"pretrain.val_fraction: expected a fraction in (0, 1), got {self.val_fraction}")
        if self.loss_region not in LOSS_REGIONS:
            raise ConfigError(f"pretrain.loss_region: expected one of {list(LOSS_REGIONS)}, got {self.loss_region!r}")
        if self.people_label not in PEOPLE_LABELS:
            raise ConfigError(f"pretrain.people_label: expected one of {list(PEOPLE_LABELS)}, "
                              f"got {self.people_label!r}")
        if len(self.future_s) != len(TARGETS) - 2 or any(s <= 0 for s in self.future_s):
            raise ConfigError(f"pretrain.future_s: expected {len(TARGETS) - 2} positive horizons (s) for the targets "
                              f"{TARGETS[2:]}, got {self.future_s}")
        if self.encoder.backbone_weights and not Path(self.encoder.backbone_weights).is_file():
            raise ConfigError(f"pretrain.encoder.backbone_weights: no file {self.encoder.backbone_weights}")
        resolve_device(self.device, "pretrain.device")  # cuda without CUDA: one error, before anything is written
        resolve_precision(self.precision, resolve_device(self.device, "pretrain.device"), "pretrain.precision")


def dataset_dir(cfg: PretrainConfig) -> Path:
    return layout.dataset_dir(cfg.data_dir, cfg.repo_id)


def checkpoint_dir(cfg: PretrainConfig) -> Path:
    return layout.checkpoint_dir(cfg.data_dir, cfg.name)


def inputs(cfg: PretrainConfig) -> list[Path]:
    """The dataset; fails here, before any output exists, when it or the grid does not fit."""

    root = dataset_dir(cfg)
    meta = check_dataset(root)
    check_grid_fits_cameras(cfg.encoder.grid, meta.cameras, "pretrain.encoder")
    check_grid_in_local_map(cfg.encoder.grid, meta.local_map, str(root))
    # only the dataset's files are inputs (not, e.g., a lock file lerobot may create)
    return [root / "meta", root / "data", root / "videos"]


def load_backbone_weights(encoder, path: str) -> None:
    """Initialises the ResNet-18 trunk from a user-given torchvision ``resnet18`` state dict (.pth / .safetensors)."""
    p = Path(path)
    sd = read_weights(p)  # missing / unreadable / damaged / non-finite -> one error naming the file
    names = ["conv1", "bn1", "relu", "maxpool", "layer1", "layer2", "layer3", "layer4"]
    mapped = {}
    for k, v in sd.items():
        head = k.split(".")[0]
        if head in names and names.index(head) < len(encoder.trunk):
            mapped[f"{names.index(head)}.{k.split('.', 1)[1]}"] = v
    missing, _ = encoder.trunk.load_state_dict(mapped, strict=False)
    if missing:
        raise CorruptArtifactError(f"backbone weights {p}: not a torchvision resnet18 state dict "
                                   f"(missing {missing[:3]}...)")
    log.info("pretrain: trunk initialised from %s", p)


def calibration_clips(store, train_slices, history: int, cfg: PretrainConfig) -> tuple[list, int]:
    """The int8 calibration's seeded whole clips of the training episodes (at least ``cfg.int8_calibration_frames``
    target frames, fewer when the episodes hold fewer) and their target frame count."""
    clips = make_clips(store, train_slices, cfg.clip_frames, history, np.random.default_rng([cfg.seed, 8]))
    order = np.random.default_rng([cfg.seed, 9]).permutation(len(clips))
    picked, n = [], 0
    for i in order:
        if n >= cfg.int8_calibration_frames:
            break
        picked.append(clips[int(i)])
        n += len(clips[int(i)][1])
    return picked, n


def int8_version(encoder: BEVEncoder, heads: PretextHeads, store, train_slices, val_slices, fov, pos_weight,
                 cfg: PretrainConfig, out: Path) -> dict:
    """Calibrates the int8 version of the trained encoder (:mod:`pretrain.quantize`, CPU) on seeded whole clips of
    the training episodes (at least ``cfg.int8_calibration_frames`` target frames), saves the calibration beside the
    weights and returns its validation metrics (loss and IoU at p > 0.5, as ``final``) for metrics.json."""
    q = QuantizedBEVEncoder(encoder)  # CPU copies of the weights
    heads_cpu = PretextHeads(cfg.encoder.bev_channels)
    heads_cpu.load_state_dict({k: v.cpu() for k, v in heads.state_dict().items()})
    heads_cpu.eval()
    picked, n = calibration_clips(store, train_slices, encoder.frames, cfg)
    with torch.no_grad():
        for batch in make_batches(picked, cfg.clips_per_batch, encoder.frames):
            forward_batch(q, heads_cpu, store, batch)  # the observers record every activation's range
    state = q.calibration_state()
    q.freeze()
    save_calibration(out, state, {"target_frames": str(n), "clips": str(len(picked))})
    metrics = evaluate(q, heads_cpu, store, val_slices, fov, torch.as_tensor(pos_weight), cfg.clip_frames,
                       cfg.clips_per_batch)
    log.info("pretrain: int8 version calibrated on %d frames; validation %s", n,
             ", ".join(f"{k} {v:.4f}" for k, v in metrics.items() if k.startswith("iou_")))
    return {"calibration_target_frames": n, "calibration_clips": len(picked), **metrics}


def int8_verdict(final: dict, int8: dict | None) -> bool | None:
    """Whether the int8 version keeps the float encoder's maps on the validation frames (None: no int8 version);
    a warning names what it loses (encoder_precision int8 then refuses it: :func:`pretrain.quantize.check_int8_version`)."""
    if int8 is None:
        return None
    losses = int8_iou_losses({"final": final, "int8": int8})
    if losses:
        log.warning("pretrain: the int8 version loses %s (float -> int8, allowed loss %.2f): encoder_precision int8 "
                    "will refuse this encoder; fp32 / bf16 / auto are unaffected",
                    ", ".join(f"{k} {f:.3f} -> {q:.3f}" for k, (f, q) in losses.items()), INT8_MAX_IOU_DROP)
    return not losses


def body(cfg: PretrainConfig, out: Path) -> dict:
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    device = resolve_device(cfg.device, "pretrain.device")
    root = dataset_dir(cfg)
    meta = check_dataset(root)
    cameras = meta.cameras
    grid = cfg.encoder.grid
    fov = check_grid_fits_cameras(grid, cameras, "pretrain.encoder")
    n_eps = int(meta.info["total_episodes"])
    if cfg.max_episodes:
        n_eps = min(n_eps, cfg.max_episodes)
    train_eps, val_eps = split_episodes(n_eps, cfg.val_fraction, cfg.seed)
    store = load_frames(root, cameras, grid, cfg.encoder.lift_stride_px, cfg.future_s,
                        episodes=list(range(n_eps)), max_gb=cfg.max_ram_gb, progress=cfg.progress,
                        people_label=cfg.people_label)
    sl = store.episode_slices
    train_slices, val_slices = [sl[e] for e in train_eps], [sl[e] for e in val_eps]

    torch.manual_seed(cfg.seed)
    encoder = BEVEncoder(cfg.encoder, cameras)
    if cfg.encoder.backbone_weights:
        load_backbone_weights(encoder, cfg.encoder.backbone_weights)
    heads = PretextHeads(cfg.encoder.bev_channels)
    encoder.to(device)  # the frames stay in host memory; fit copies each batch over
    heads.to(device)
    log.info("pretrain: training on %s", device)
    fc = FitConfig(epochs=cfg.epochs, clip_frames=cfg.clip_frames, clips_per_batch=cfg.clips_per_batch, lr=cfg.lr,
                   weight_decay=cfg.weight_decay, warmup_frac=cfg.warmup_frac,
                   checkpoint_every_steps=cfg.checkpoint_every_steps, log_every_steps=cfg.log_every_steps,
                   seed=cfg.seed, config_hash=config_hash(cfg), pos_weight_cap=cfg.pos_weight_cap,
                   loss_region=cfg.loss_region,
                   precision=resolve_precision(cfg.precision, device, "pretrain.precision"))
    result = fit(encoder, heads, store, train_slices, val_slices, fov, fc, out, resume=True, progress=cfg.progress)
    history = result["history"]
    final = history[-1] if history else evaluate(encoder, heads, store, val_slices, fov,
                                                 torch.tensor(result["pos_weight"]), cfg.clip_frames,
                                                 cfg.clips_per_batch)
    encoder.eval()
    heads.eval()
    n_train = sum(b - a for a, b in train_slices)
    write_encoder_checkpoint(out, encoder, heads, {  # saved from CPU copies: loads on any machine
        "targets": list(TARGETS), "future_s": list(cfg.future_s), "people_label": cfg.people_label,
        "loss_region": cfg.loss_region,
        "dataset": {"repo_id": cfg.repo_id, "train_episodes": train_eps, "val_episodes": val_eps},
        "trained_steps": result["step"], "fps": meta.fps})
    # the decision rule: per-target thresholds chosen on the validation episodes, scored cross-fitted (honest)
    inter, union = episode_counts(encoder, heads, store, val_slices, fov, CAL_THRESHOLDS, cfg.clip_frames,
                                  cfg.clips_per_batch)
    decision = json_safe(calibrate(inter, union, CAL_THRESHOLDS, result["pos_weight"]))
    int8 = (int8_version(encoder, heads, store, train_slices, val_slices, fov, result["pos_weight"], cfg, out)
            if cfg.int8_calibration_frames else None)
    atomic_write_json(out / METRICS_JSON, {
        "int8": int8, "int8_usable": int8_verdict(final, int8),
        "final": final, "history": history, "targets": list(TARGETS), "iou": "dataset-level IoU at p > 0.5 over "
        "validation frames, cells in the cameras' field of view only", "pos_weight": result["pos_weight"],
        "decision": decision, "thresholds": decision["best_threshold"],
        "train_frames": n_train, "val_frames": sum(b - a for a, b in val_slices), "steps": result["step"],
        "fov_fraction": float(fov.mean()), **device_counts(device)})

    # figures: evenly spaced validation frames
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    plot_fov(fig_dir / "fov.png", grid, fov)
    plot_curves(fig_dir / "curves.png", out / "train_log.csv", history)
    val_idx = np.concatenate([np.arange(a, b) for a, b in val_slices])
    picks = list(val_idx[np.linspace(0, len(val_idx) - 1, cfg.figures).astype(int)]) if cfg.figures else []
    names = [f"sample_{k}.png" for k in range(len(picks))]
    turning = turning_pedestrian_frame(store, val_slices, fov, grid.x_bound[2]) if cfg.figures else None
    if turning is not None:
        picks.append(turning[0])
        names.append("turning_pedestrian.png")

    with torch.no_grad():
        for k, t in enumerate(picks):
            start = int(store.episode_start[t])
            frames = np.maximum(np.arange(t - encoder.frames + 1, t + 1), start)
            batch = Batch(frames, np.arange(encoder.frames)[None], np.array([t]))
            logits, labels, valid = forward_batch(encoder, heads, store, batch)
            ep = int(np.searchsorted([a for a, _ in sl], t, side="right") - 1)
            what = (f"a pedestrian turning {turning[1]:.0f}° between +0.5 s and +1.0 s, "
                    if names[k] == "turning_pedestrian.png" else "")
            plot_sample(fig_dir / names[k], grid, [c.name for c in cameras], store.rgb[t],
                        store.depth[t], labels[0].cpu().numpy(), torch.sigmoid(logits[0]).cpu().numpy(),
                        valid[0].cpu().numpy(), fov,
                        f"{what}validation episode {ep}, frame {t - start} — step {result['step']}")
    counts = {"steps": result["step"], "train_frames": n_train, "val_frames": int(len(val_idx)),
              "episodes": n_eps, "precision": fc.precision, **device_counts(device)}
    for key, v in final.items():
        if key.startswith(("iou_", "val_loss")) and not (isinstance(v, float) and math.isnan(v)):
            counts[key] = round(float(v), 4)
    for k, t in enumerate(TARGETS):
        v = decision["cross_fitted"][k]
        if v is not None:
            counts[f"iou_calibrated_{t}"] = round(float(v), 4)
    log.info("pretrain: validation %s", ", ".join(f"{k} {v}" for k, v in counts.items() if k.startswith("iou_")))
    return counts
