"""The pretext training loop of the BEV encoder (readable top to bottom, cleanrl-style signposts).

One optimisation step takes a batch of clips (consecutive frames of one episode each, T−1 frames of context
before the targets), encodes every frame of the clips once with the image backbone and the lift, then fuses the
window of T frames ending at each target (ego-motion warp + temporal model) and scores the pretext heads against
the labels with a per-target binary cross-entropy restricted to the cameras' field of view (and, for the future
targets, to frames whose future lies inside the episode).

Resume: the state (weights, optimizer, scheduler, torch RNG, step) is saved atomically every
``checkpoint_every_steps`` steps and at every epoch end; the batch order of epoch ``e`` depends only on
``(seed, e)``, so a resumed run skips the batches it already did and continues exactly where it stopped.

Device: everything runs where the encoder's parameters are (the caller moves encoder and heads there, e.g.
``pretrain.device``); the frames stay in host memory (:class:`pretrain.data.FrameStore`) and each batch is copied
over as it is used (uint8 images: converted to float on the device). The saved state holds CPU tensors, so a run
started on a GPU resumes on a CPU (and back): :func:`load_state` maps to the CPU and ``load_state_dict`` copies
into the modules and the optimizer wherever they are.
"""

from __future__ import annotations

import csv
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from pipeline.core.artifacts import atomic_write_with
from pipeline.core.device import autocast, cpu_state
from pipeline.core.errors import ConfigError, CorruptArtifactError
from pretrain.data import FrameStore, make_batches, make_clips
from pretrain.model import TARGETS, BEVEncoder, PretextHeads
from pretrain.schedule import one_cycle

log = logging.getLogger("icrowdnav")

LOG_FIELDS = ["step", "epoch", "lr", "loss", *[f"loss_{t}" for t in TARGETS], "frames_per_s"]


@dataclass
class FitConfig:
    """The optimisation settings :func:`fit` reads (a view of the stage config)."""

    epochs: int
    clip_frames: int
    clips_per_batch: int
    lr: float
    weight_decay: float
    warmup_frac: float
    checkpoint_every_steps: int
    log_every_steps: int
    seed: int
    config_hash: str
    pos_weight_cap: float = 10.0  # upper bound of the per-target BCE positive weight (positive_weights)
    loss_region: str = "fov"  # the cells the loss reads: LOSS_REGIONS (validation IoU stays on the field of view)
    precision: str = "fp32"  # the training forward pass: fp32 | bf16 (autocast; pipeline.core.device.autocast)


# where the training loss reaches: the cameras' field of view, or the whole grid (beyond the view the labels are still
# known — the simulator's ground truth — so the temporal model can learn to carry what left the view and the prior
# for what was never seen, instead of an unsupervised extrapolation; pretrain.evaluate --region outside)
LOSS_REGIONS = ("fov", "grid")


def loss_mask(fov: np.ndarray, region: str) -> np.ndarray:
    """The ``X x Y`` bool mask of the cells the training loss reads (:data:`LOSS_REGIONS`)."""
    if region not in LOSS_REGIONS:
        raise ConfigError(f"pretrain.loss_region: expected one of {list(LOSS_REGIONS)}, got {region!r}")
    return fov if region == "fov" else np.ones_like(fov)


def positive_weights(store: FrameStore, slices: list[tuple[int, int]], fov: np.ndarray,
                     cap: float = 10.0) -> torch.Tensor:
    """Per-target BCE ``pos_weight`` = sqrt(negatives / positives) in the field of view, clipped to [1, cap]."""
    idx = np.concatenate([np.arange(a, b) for a, b in slices])
    lab = store.labels[idx][:, :, fov]  # F x K x cells
    valid = store.valid[idx]
    out = []
    for k in range(lab.shape[1]):
        v = lab[valid[:, k], k]
        pos = float(v.sum())
        neg = float(v.size - pos)
        out.append(min(cap, max(1.0, math.sqrt(neg / pos))) if pos > 0 else 1.0)
    return torch.tensor(out)


def device_of(module: torch.nn.Module) -> torch.device:
    """The device of a module's parameters (where :func:`fit` and :func:`evaluate` compute)."""
    return next(module.parameters()).device


def to_device(t: torch.Tensor, device: torch.device) -> torch.Tensor:
    """A host tensor on ``device``: itself on the CPU; for CUDA copied through pinned memory without blocking the
    host (the copy overlaps with gathering the next array of the batch)."""
    if device.type == "cpu":
        return t
    return (t.pin_memory() if device.type == "cuda" else t).to(device, non_blocking=True)


def batch_tensors(store: FrameStore, batch, device: torch.device | None = None) -> tuple[torch.Tensor, ...]:
    """The arrays of a batch gathered from the store, on ``device`` (default: the CPU).

    Returns:
        ``rgb`` ``M x N x 3 x H x W`` uint8, ``depth`` ``M x N x h x w`` (lift pixels), ``poses`` ``M x 3`` of the
        batch's M frames; ``labels`` ``P x K x X x Y`` float and ``valid`` ``P x K`` bool of its P targets.
    """
    device = torch.device("cpu") if device is None else torch.device(device)
    rgb = to_device(torch.from_numpy(store.rgb[batch.frames]), device)
    depth = to_device(torch.from_numpy(store.depth[batch.frames]), device)
    poses = to_device(torch.from_numpy(store.pose[batch.frames]), device)
    labels = to_device(torch.from_numpy(store.labels[batch.targets]), device).float()
    valid = to_device(torch.from_numpy(store.valid[batch.targets]), device)
    return rgb, depth, poses, labels, valid


def forward_batch(encoder: BEVEncoder, heads: PretextHeads, store: FrameStore, batch) -> tuple[torch.Tensor, ...]:
    """Logits ``P x K x X x Y`` of a batch's targets, with their labels and validity (on the encoder's device)."""
    device = device_of(encoder)
    rgb, depth, poses, labels, valid = batch_tensors(store, batch, device)
    maps = encoder.encode_frames(rgb, depth)  # M x C x X x Y, each in its own frame
    win = to_device(torch.from_numpy(batch.windows), device)
    s_bev = encoder.fuse(maps[win], poses[win])  # P x C x X x Y in each target's frame
    return heads(s_bev), labels, valid


def masked_bce(logits: torch.Tensor, labels: torch.Tensor, valid: torch.Tensor, fov: torch.Tensor,
               pos_weight: torch.Tensor) -> torch.Tensor:
    """Per-target mean BCE over valid frames and field-of-view cells: returns ``K`` losses."""
    per = F.binary_cross_entropy_with_logits(logits, labels, reduction="none",
                                             pos_weight=pos_weight.view(1, -1, 1, 1))
    mask = valid[:, :, None, None].float() * fov[None, None].float()
    return (per * mask).sum((0, 2, 3)) / mask.sum((0, 2, 3)).clamp_min(1.0)


def iou_counts(logits: torch.Tensor, labels: torch.Tensor, valid: torch.Tensor, fov: torch.Tensor,
               thresholds: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Intersection and union counts ``S x K`` per threshold and target (valid frames, field-of-view cells).

    Args:
        logits, labels: ``P x K x X x Y``; valid: ``P x K``; fov: ``X x Y`` bool.
        thresholds: ``S x K`` probability thresholds (one per target, per row).
    """
    m = (valid[:, :, None, None] & fov[None, None]).unsqueeze(0)
    pred = (torch.sigmoid(logits).unsqueeze(0) > thresholds.view(*thresholds.shape, 1, 1, 1).transpose(1, 2)) & m
    true = (labels > 0.5).unsqueeze(0) & m
    return (pred & true).sum((1, 3, 4)).double(), (pred | true).sum((1, 3, 4)).double()


@torch.no_grad()
def evaluate(encoder: BEVEncoder, heads: PretextHeads, store: FrameStore, slices: list[tuple[int, int]],
             fov: np.ndarray, pos_weight: torch.Tensor, clip_frames: int, clips_per_batch: int) -> dict[str, float]:
    """Validation: loss and IoU (threshold 0.5, dataset-level, field of view only) per target (on the encoder's
    device)."""
    was = encoder.training, heads.training
    encoder.eval()
    heads.eval()
    device = device_of(encoder)
    fov_t = torch.from_numpy(fov).to(device)
    pos_weight = pos_weight.to(device)
    inter = torch.zeros(len(TARGETS), dtype=torch.float64, device=device)
    union = torch.zeros(len(TARGETS), dtype=torch.float64, device=device)
    losses, weights = torch.zeros(len(TARGETS), dtype=torch.float64, device=device), 0
    batches = make_batches(make_clips(store, slices, clip_frames, encoder.frames, None), clips_per_batch,
                           encoder.frames)
    for batch in batches:
        logits, labels, valid = forward_batch(encoder, heads, store, batch)
        losses += masked_bce(logits, labels, valid, fov_t, pos_weight).double() * len(batch.targets)
        weights += len(batch.targets)
        i, u = iou_counts(logits, labels, valid, fov_t, torch.full((1, len(TARGETS)), 0.5, device=device))
        inter += i[0]
        union += u[0]
    encoder.train(was[0])
    heads.train(was[1])
    inter, union = inter.cpu(), union.cpu()
    out = {"val_loss": float((losses / max(weights, 1)).mean())}
    for k, t in enumerate(TARGETS):
        out[f"iou_{t}"] = float(inter[k] / union[k]) if union[k] > 0 else float("nan")
    out["val_frames"] = sum(b - a for a, b in slices)
    return out


def save_state(path: Path, state: dict[str, Any]) -> None:
    """Atomic ``torch.save`` (temporary file, fsync, rename) of the state with every tensor on the CPU (a state saved
    during a GPU run loads anywhere)."""
    atomic_write_with(path, lambda f: torch.save(cpu_state(state), f))


def load_state(path: Path) -> dict[str, Any]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises RuntimeError, UnpicklingError, EOFError, ... for a broken file
        raise CorruptArtifactError(f"corrupt training state {path}: {type(e).__name__}: {str(e)[:200]}") from None
    need = {"step", "epoch", "batch_in_epoch", "encoder", "heads", "optimizer", "scheduler", "torch_rng",
            "config_hash", "history"}
    if not isinstance(state, dict) or not need <= set(state):
        raise CorruptArtifactError(f"corrupt training state {path}: expected keys {sorted(need)}")
    return state


def _rewrite_log(path: Path, upto_step: int) -> None:
    """Drops log rows written after the saved state (they will be redone by the resumed run)."""
    if not path.is_file():
        return
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if int(r["step"]) <= upto_step]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=LOG_FIELDS)
        w.writeheader()
        w.writerows(rows)


def fit(encoder: BEVEncoder, heads: PretextHeads, store: FrameStore, train_slices: list[tuple[int, int]],
        val_slices: list[tuple[int, int]], fov: np.ndarray, fc: FitConfig, out: Path, resume: bool,
        stop_at_step: int | None = None, progress: bool = True,
        on_epoch: Callable[[int, dict[str, float]], None] | None = None) -> dict[str, Any]:
    """Trains encoder + heads on the pretext targets; returns ``{"step", "history", "pos_weight", ...}``.

    Args:
        encoder, heads: the modules (trained in place, on the device they are on; move both there first).
        store: all frames; ``train_slices`` / ``val_slices``: store ranges of the train / validation episodes.
        fov: ``X x Y`` bool field-of-view mask (IoU is restricted to it; so is the loss unless ``fc.loss_region`` is
            ``grid``).
        fc: optimisation settings.
        out: the checkpoint directory (``state/``, ``train_log.csv``, ``tb/`` are written here).
        resume: continue from ``out/state/last.pt`` when it exists.
        stop_at_step: stop (after saving the state) once this many steps are done — simulates a kill in tests.
        progress: show a progress bar.
        on_epoch: called with ``(epoch, validation metrics)`` after each epoch's validation.
    """
    from torch.utils.tensorboard import SummaryWriter
    from tqdm import tqdm

    torch.manual_seed(fc.seed)
    device = device_of(encoder)
    mask = loss_mask(fov, fc.loss_region)
    mask_t = torch.from_numpy(mask).to(device)
    pos_weight = positive_weights(store, train_slices, mask, fc.pos_weight_cap)
    pos_weight_d = pos_weight.to(device)
    params = list(encoder.parameters()) + list(heads.parameters())
    optim = torch.optim.AdamW(params, lr=fc.lr, weight_decay=fc.weight_decay)
    # exact number of steps (the clips of epoch e depend only on (seed, e)), so the schedule ends where training does
    total = max(1, sum(math.ceil(len(make_clips(store, train_slices, fc.clip_frames, encoder.frames,
                                                np.random.default_rng([fc.seed, e]))) / fc.clips_per_batch)
                       for e in range(fc.epochs)))
    sched = one_cycle(optim, fc.lr, total, pct_start=fc.warmup_frac)
    state_path = out / "state" / "last.pt"
    log_path = out / "train_log.csv"
    step, epoch0, skip, history = 0, 0, 0, []
    if resume and state_path.is_file():
        st = load_state(state_path)
        if st["config_hash"] != fc.config_hash:
            raise ConfigError(f"cannot resume {out}: its training state was made with another config "
                              f"(config_hash {st['config_hash'][:12]} there, {fc.config_hash[:12]} now); "
                              "use --overwrite to start again")
        encoder.load_state_dict(st["encoder"])
        heads.load_state_dict(st["heads"])
        optim.load_state_dict(st["optimizer"])
        sched.load_state_dict(st["scheduler"])
        torch.set_rng_state(st["torch_rng"])
        step, epoch0, skip, history = st["step"], st["epoch"], st["batch_in_epoch"], list(st["history"])
        log.info("pretrain: resuming %s at step %d (epoch %d, batch %d)", out, step, epoch0, skip)
        _rewrite_log(log_path, step)
    elif log_path.exists():
        log_path.unlink()
    writer = SummaryWriter(str(out / "tb"), purge_step=step + 1 if step else None)
    new_log = not log_path.is_file()
    log_file = open(log_path, "a", newline="")
    csv_w = csv.DictWriter(log_file, fieldnames=LOG_FIELDS)
    if new_log:
        csv_w.writeheader()

    def checkpoint(epoch: int, batch_in_epoch: int) -> None:
        save_state(state_path, {
            "step": step, "epoch": epoch, "batch_in_epoch": batch_in_epoch, "encoder": encoder.state_dict(),
            "heads": heads.state_dict(), "optimizer": optim.state_dict(), "scheduler": sched.state_dict(),
            "torch_rng": torch.get_rng_state(), "config_hash": fc.config_hash, "history": history})
        log_file.flush()

    try:
        for epoch in range(epoch0, fc.epochs):
            # the epoch's clips and their order depend only on (seed, epoch): resuming replays them exactly
            rng = np.random.default_rng([fc.seed, epoch])
            clips = make_clips(store, train_slices, fc.clip_frames, encoder.frames, rng)
            order = rng.permutation(len(clips))
            batches = make_batches([clips[i] for i in order], fc.clips_per_batch, encoder.frames)
            start = skip if epoch == epoch0 else 0
            encoder.train()
            heads.train()
            bar = tqdm(total=len(batches), initial=start, desc=f"pretrain epoch {epoch + 1}/{fc.epochs}",
                       unit="batch", disable=not progress)
            for bi in range(start, len(batches)):
                t0 = time.perf_counter()
                with autocast(device, fc.precision):
                    logits, labels, valid = forward_batch(encoder, heads, store, batches[bi])
                losses = masked_bce(logits.float(), labels, valid, mask_t, pos_weight_d)
                loss = losses.mean()
                optim.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(params, 5.0)
                optim.step()
                if sched.last_epoch + 1 < total:
                    sched.step()
                step += 1
                loss_value = loss.item()  # waits for the device: the step's time below is its real time
                fps = len(batches[bi].targets) / (time.perf_counter() - t0)
                bar.update(1)
                bar.set_postfix(loss=f"{loss_value:.3f}")
                if step % fc.log_every_steps == 0 or bi == len(batches) - 1:
                    row = {"step": step, "epoch": epoch, "lr": optim.param_groups[0]["lr"], "loss": loss_value,
                           "frames_per_s": round(fps, 2)}
                    row.update({f"loss_{t}": float(losses[k].detach()) for k, t in enumerate(TARGETS)})
                    csv_w.writerow(row)
                    for k, v in row.items():
                        if k not in ("step", "epoch"):
                            writer.add_scalar(f"train/{k}", v, step)
                if step % fc.checkpoint_every_steps == 0 and bi + 1 < len(batches):
                    checkpoint(epoch, bi + 1)
                if stop_at_step is not None and step >= stop_at_step:
                    checkpoint(epoch, bi + 1)
                    bar.close()
                    return {"step": step, "history": history, "stopped": True, "pos_weight": pos_weight.tolist()}
            bar.close()
            metrics = evaluate(encoder, heads, store, val_slices, fov, pos_weight, fc.clip_frames,
                               fc.clips_per_batch)
            metrics.update({"epoch": epoch + 1, "step": step})
            history.append(metrics)
            for k, v in metrics.items():
                if k.startswith(("iou_", "val_loss")):
                    writer.add_scalar(f"val/{k}", v, step)
            log.info("pretrain: epoch %d/%d, step %d: %s", epoch + 1, fc.epochs, step,
                     ", ".join(f"{k} {v:.3f}" for k, v in metrics.items() if k.startswith(("iou_", "val_loss"))))
            if on_epoch is not None:
                on_epoch(epoch, metrics)
            checkpoint(epoch + 1, 0)
    finally:
        log_file.close()
        writer.close()
    return {"step": step, "history": history, "stopped": False, "pos_weight": pos_weight.tolist()}
