"""Training the ViNT-style baseline (package docstring): minibatches of clips, ViNT's losses, the train entry point."""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from pipeline.core.errors import InputMissingError
from pretrain.data import split_episodes
from rl.baselines.common import save_baseline
from rl.baselines.vint.configuration import NAME, Config
from rl.baselines.vint.data import (
    Frames,
    check_dataset,
    context_indices,
    dataset_root,
    goal_features,
    load_dataset,
    trajectory_labels,
)
from rl.baselines.vint.model import ViNTStyle, build_model
from rl.baselines.vint.weights import load_released_weights


@dataclass
class Batch:
    """Tensors of one minibatch: ``frames`` (the unique images), ``window`` (``B x (P+1)`` rows of ``frames``),
    ``goal`` ``B x 3``, ``waypoints`` ``B x H x 4``, ``dist`` ``B``."""

    frames: torch.Tensor
    window: torch.Tensor
    goal: torch.Tensor
    waypoints: torch.Tensor
    dist: torch.Tensor


class Trainer:
    """Minibatches and loss of ViNT-style imitation on :class:`Frames` (see the package docstring).

    Args:
        frames: the data. cfg: the options. metres_per_step: the waypoint normalisation.
    """

    def __init__(self, frames: Frames, cfg: Config, metres_per_step: float) -> None:
        self.frames, self.cfg, self.metres_per_step = frames, cfg, metres_per_step
        self.start, self.end = frames.bounds()

    def clips(self, episodes: list[int], rng: np.random.Generator | None) -> list[np.ndarray]:
        """Targets of ``episodes`` cut into clips of ``clip_len`` consecutive frames (shuffled when ``rng``)."""
        out = [np.arange(s, e)[i:i + self.cfg.clip_len] for s, e in (self.frames.slices[k] for k in episodes)
               for i in range(0, e - s, self.cfg.clip_len)]
        if rng is not None:
            out = [out[i] for i in rng.permutation(len(out))]
        return out

    def batch(self, targets: np.ndarray, mirror: bool) -> Batch:
        c = self.cfg
        ctx = context_indices(targets, self.start[targets], c.context, c.spacing)
        uniq, inv = np.unique(ctx, return_inverse=True)
        wp, dist, goal = trajectory_labels(self.frames.pose, self.frames.goal, targets, self.end[targets],
                                           c.horizon, c.spacing, self.metres_per_step, c.max_dist)
        images = self.frames.images[uniq]
        if mirror:  # flip each camera and swap them; the mirror world has y, yaw and the goal's y negated
            w = images.shape[-1] // 2
            images = np.concatenate([images[..., w:][..., ::-1], images[..., :w][..., ::-1]], -1)
            wp = wp * np.array([1, -1, 1, -1], np.float32)
            goal = goal * np.array([1, -1], np.float32)
        return Batch(torch.from_numpy(np.ascontiguousarray(images)), torch.from_numpy(inv.reshape(ctx.shape)),
                     torch.from_numpy(goal_features(goal, c.goal_scale_m)), torch.from_numpy(wp),
                     torch.from_numpy(dist))

    def loss(self, model: ViNTStyle, b: Batch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(total, waypoint MSE, distance MSE): ViNT's ``alpha * 1e-2 * dist + (1 - alpha) * action``."""
        dist, wp = model.head(model.encode(b.frames)[b.window], b.goal)
        action_loss = F.mse_loss(wp, b.waypoints)
        dist_loss = F.mse_loss(dist, b.dist)
        return self.cfg.alpha * 1e-2 * dist_loss + (1 - self.cfg.alpha) * action_loss, action_loss, dist_loss

    def evaluate(self, model: ViNTStyle, episodes: list[int]) -> dict[str, float]:
        """Mean losses over every frame of ``episodes`` (eval mode, no mirroring)."""
        model.eval()
        sums, n = np.zeros(3), 0
        with torch.no_grad():
            for clip_group in groups(self.clips(episodes, None), self.cfg.clips_per_batch):
                targets = np.concatenate(clip_group)
                sums += len(targets) * np.array([v.item() for v in self.loss(model, self.batch(targets, False))])
                n += len(targets)
        model.train()
        return dict(zip(("loss", "action_loss", "dist_loss"), (sums / max(n, 1)).tolist(), strict=True))

    def fit(self, model: ViNTStyle, train_eps: list[int], val_eps: list[int], seed: int, log=None,
            progress: bool = False) -> dict[str, Any]:
        """Trains ``model`` for ``cfg.epochs``; logs ``train`` / ``val`` rows through ``log.add`` when given.

        Returns the history (``train_loss`` per epoch, ``val`` losses per epoch), ``steps`` and ``frames_per_s``.
        """
        c = self.cfg
        rng = np.random.default_rng(seed)
        torch.manual_seed(seed)
        per_epoch = math.ceil(len(self.clips(train_eps, None)) / c.clips_per_batch)
        opt = torch.optim.AdamW(model.parameters(), lr=c.lr, weight_decay=c.weight_decay)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, per_epoch * c.epochs))
        hist: dict[str, Any] = {"train_loss": [], "val": []}
        step, seen, t0 = 0, 0, time.perf_counter()
        model.train()
        bar = tqdm(total=per_epoch * c.epochs, desc="vint: train", unit="batch", disable=not progress,
                   dynamic_ncols=True)
        for epoch in range(c.epochs):
            total, count = 0.0, 0
            for clip_group in groups(self.clips(train_eps, rng), c.clips_per_batch):
                targets = np.concatenate(clip_group)
                loss, a_loss, d_loss = self.loss(model, self.batch(targets, c.mirror and rng.random() < 0.5))
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                sched.step()
                step += 1
                seen += len(targets)
                total += loss.item() * len(targets)
                count += len(targets)
                if log is not None and step % 20 == 0:
                    log.add("train", step, loss=loss.item(), action_loss=a_loss.item(), dist_loss=d_loss.item(),
                            lr=sched.get_last_lr()[0])
                bar.update()
                bar.set_postfix(epoch=epoch, loss=f"{loss.item():.4f}")
            hist["train_loss"].append(total / max(count, 1))
            val = self.evaluate(model, val_eps) if val_eps else {}
            hist["val"].append(val)
            if log is not None:
                log.add("epoch", epoch + 1, train_loss=hist["train_loss"][-1], **{f"val_{k}": v for k, v in val.items()})
        bar.close()
        model.eval()
        wall = time.perf_counter() - t0
        return {**hist, "steps": step, "frames_per_s": round(seen / max(wall, 1e-9), 1), "wall_s": round(wall, 1)}


def groups(items: list, size: int) -> list[list]:
    """``items`` in consecutive groups of ``size`` (the last may be shorter): clips into minibatches."""
    return [items[i:i + size] for i in range(0, len(items), size)]


def inputs(cfg) -> list[Path]:
    """The dataset's metadata, parquet and video files (and ``init_weights``); a missing dataset ->
    InputMissingError naming it and `make record`."""
    cfg.vint.validate()
    root = dataset_root(cfg)
    check_dataset(root)
    files = [root / "meta" / "info.json", *sorted(root.glob("data/**/*.parquet")),
             *sorted(root.glob("videos/observation.images.*/**/*.mp4"))]
    if cfg.vint.init_weights:
        w = Path(cfg.vint.init_weights)
        if not w.is_file():
            raise InputMissingError(f"train.vint.init_weights: {w} does not exist")
        files.append(w)
    return files


def train(cfg, out: Path, log) -> dict[str, Any]:
    """Imitation of the recorded expert (package docstring); writes ``policy.safetensors`` / ``policy.json``.

    ``out`` receives::

        policy.safetensors, policy.json   the weights; net, deploy (spacing, fps, metres_per_step, waypoint_index,
                                          goal_scale_m, max_dist), produced_by (the budget)
    """
    c: Config = cfg.vint
    c.validate()
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    t0 = time.perf_counter()
    root = dataset_root(cfg)
    frames, fps = load_dataset(root, c.image_hw, c.episodes, cfg.progress)
    log_load_s = time.perf_counter() - t0
    train_eps, val_eps = split_episodes(len(frames.slices), c.val_fraction, cfg.seed)
    metres_per_step = cfg.sim.robot.v_max_mps * c.spacing / fps
    torch.manual_seed(cfg.seed)
    model = build_model(c.net())
    released = load_released_weights(model, Path(c.init_weights)) if c.init_weights else None
    trainer = Trainer(frames, c, metres_per_step)
    hist = trainer.fit(model, train_eps, val_eps, cfg.seed, log, cfg.progress)
    deploy = {"spacing": c.spacing, "fps": fps, "metres_per_step": metres_per_step,
              "waypoint_index": c.waypoint_index, "goal_scale_m": c.goal_scale_m, "max_dist": c.max_dist}
    budget = {"dataset": str(root), "episodes": len(frames.slices), "frames": len(frames.pose),
              "train_episodes": len(train_eps), "val_episodes": len(val_eps), "epochs": c.epochs,
              "steps": hist["steps"], "load_s": round(log_load_s, 1), "train_s": hist["wall_s"],
              "wall_s": round(time.perf_counter() - t0, 1), "frames_per_s": hist["frames_per_s"],
              "init_weights": c.init_weights or None}
    inputs_desc = {"images": f"rgb_left | rgb_right resized to {c.image_hw} each, side by side, uint8",
                   "context": f"{c.context} past frames every {c.spacing} dataset frames + the current one",
                   "goal": "goal or waypoint in the robot frame: cos, sin, tanh(d / goal_scale_m)"}
    save_baseline(out, NAME, model, c.net(), inputs_desc, budget, deploy=deploy, released_weights=released)
    val = hist["val"][-1] if hist["val"] else {}
    return {"budget": budget, "train_loss": hist["train_loss"], "val": val}
