"""The intention model: where a tracked pedestrian walks next, from its track and the pose the robot detects on it.

``icrowdnav pretrain-intention`` (the second target of ``make pretrain``, beside the BEV encoder) trains it on a
recorded LeRobot dataset and writes ``DATA_DIR/checkpoints/intention/``; the students' lookahead head loads it frozen
to predict the people it perceives (:mod:`rl.perceive`) instead of extrapolating their velocity.

**Inputs are what a robot has, the target is what the simulator knows.** Each episode of the dataset is replayed
through the students' own tracker (:class:`sim.tracking.PedestrianTracker` over the detected poses and the odometry,
exactly as :mod:`rl.perceive` runs it online). For every live track at every frame the model reads, in the *track's
frame* (origin at the track, x along its estimated velocity, or along the viewing ray when it stands):

* ``hist`` ``H x 2`` its filtered positions over the last ``H`` frames and ``hist_valid`` which of them it lived;
* ``speed`` its estimated speed;
* ``kp`` ``17 x 3`` / ``kp_mask`` the keypoints detected on it this frame (none when it coasts), through the
  I²Former's pose encoder (φ_p + joint embedding + IntentFormer, :class:`pretrain.i2former.I2Former`);

and predicts its displacement at ``horizons_s`` (0.2 … 2.0 s) as constant velocity + a learned residual. The target
is the true future position (``privileged.ped_state``) of the pedestrian nearest to the track (within
:data:`MATCH_M`), relative to the track's current estimate; an auxiliary head regresses the true head yaw from the
pose features (the cue our humans announce turns with, :mod:`sim.intention`).

**Why the pose part is a gated residual with dropout.** The intention probe (:mod:`pretrain.probe`) found that a
model given noisy detected keypoints beside the past positions ends *behind* positions alone. Here the positions
part (``base``) and the pose part (``pose_residual``) are separate heads; during training the pose residual is
dropped for a fraction ``pose_dropout`` of the samples, so ``base`` alone is a complete forecaster and the pose can
only add to it. Four models are fitted with the same recipe and reported side by side on the validation episodes
(split by episode), against constant velocity: ``position`` (no pose), ``pose`` (detected keypoints: what the
students load), and two references that are evaluated, not saved — ``pose_centroid`` (every detected joint moved to
their mean: the detection's fresh position without the body's shape, so ``pose`` − ``pose_centroid`` is what the
pose's *shape* adds) and ``pose_true`` (the simulator's keypoints: the ceiling of what the pose holds). Errors
are ADE over the horizons, FDE at 1.0 and 2.0 s, over all samples and over turn events (the true
walking direction turns by ≥ 45° within 1.0 s), with 95 % bootstrap intervals over validation episodes.

**Frozen or fine-tuned.** ``train`` loads the model frozen by default; with ``--intention_tune.epochs N`` it
fine-tunes it after every DAgger iteration on that student's own rollouts (:func:`finetune_forecaster`: the same
pretext, the people as they move around the student's robot), writes it into the policy's checkpoint and rolls out the
next iteration with it. Only the pretext is fine-tuned: the lookahead head reads the model's predictions through a
parameter-free rollout, so no policy gradient reaches it. Measured on the default profile's ``full`` rollouts, the
fine-tuning changes the held-out error by < 1 % (docs/results.md, the intention model), hence the default.

Tree (``DATA_DIR/checkpoints/<name>/``)::

    forecaster.safetensors   the pose model (what ``train`` loads)
    position.safetensors     the position-only model (the reference the pose model must beat)
    intention.json           model config, horizons, history, frame rate, dataset split, which file is which
    metrics.json / .md       validation errors per model and group, bootstrap intervals, counts, timings
    train_log.csv            model, epoch, training loss, validation FDE
    figures/errors.png       FDE by group and model; figures/turn_<k>.png a turning pedestrian, predicted vs true
    config.yaml, manifest.json (written last by the stage runner)
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from pipeline.core import layout
from pipeline.core.artifacts import atomic_write_json, atomic_write_text, json_safe
from pipeline.core.config import BaseStageConfig, check_run_name
from pipeline.core.device import device_counts, resolve_device
from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from pipeline.core.keys import OBS_ODOM, OBS_POSE_MASK, OBS_POSES, PRIV_PED_KEYPOINTS, PRIV_PED_STATE
from pipeline.core.manifest import MANIFEST_NAME
from pretrain.checkpoint import load_safetensors, save_safetensors
from pretrain.data import split_episodes
from pretrain.figures import plot_model_errors, pyplot
from pretrain.i2former import N_JOINTS, POSE_SCALE_M, I2Former, I2FormerConfig, mlp
from pretrain.probe import read_episodes
from pretrain.schedule import one_cycle
from recorder.dataset_info import read_dataset_info
from sim.geometry import robot_to_world, wrap_angle
from sim.tracking import PedestrianTracker, person_detections
from sim.viz import save_figure

log = logging.getLogger("icrowdnav")

FORMAT_VERSION = 1
FORECASTER_WEIGHTS = "forecaster.safetensors"
POSITION_WEIGHTS = "position.safetensors"
INTENTION_JSON = "intention.json"
METRICS_JSON = "metrics.json"
TUNED_FROM = "tuned_from"  # intention.json key of a forecaster fine-tuned inside a training run (finetune_forecaster)
KP_SCALE_M = 0.5  # track-frame keypoints enter the pose encoder in units of this (a body's half width)
MATCH_M = 0.5  # a track is labelled with the true pedestrian nearest to it within this distance
STANDING_MPS = 0.2  # below this estimated speed the track frame's x axis is the viewing ray, not the velocity
TURN_DEG = 45.0  # turn event: the true walking direction changes by at least this within TURN_WINDOW_S
TURN_WINDOW_S = 1.0
MIN_TURN_SPEED = 0.3  # m/s at both ends of the window (a standing person has no walking direction)
LEAD_BINS_S = ((0.0, 0.3), (0.3, 0.6), (0.6, 1.01))
# fitted models: name -> where its keypoints come from (None: no pose); pose_centroid and pose_true are references
MODELS = {"position": None, "pose": "detected", "pose_centroid": "centroid", "pose_true": "true"}


@dataclass
class ForecasterConfig:
    """Sizes of the intention model (stored in ``intention.json``)."""

    history: int = 8  # past track positions read (frames)
    horizons_s: list[float] = field(default_factory=lambda: [round(0.2 * k, 1) for k in range(1, 11)])
    dim: int = 32  # I²Former width (pose encoder)
    hidden: int = 64  # width of the MLP heads
    pose: bool = True  # read the detected keypoints (False: the position-only model)

    def validate(self, where: str = "intention.model") -> None:
        if self.history < 2 or self.dim < 4 or self.hidden < 4 or self.dim % 4:
            raise ConfigError(f"{where}: expected history >= 2, hidden >= 4, dim >= 4 and divisible by 4, got "
                              f"history={self.history}, dim={self.dim}, hidden={self.hidden}")
        hs = self.horizons_s
        bad = any(not (math.isfinite(h) and h > 0) for h in hs)
        if not hs or bad or sorted(hs) != list(hs) or len(set(hs)) < len(hs):
            raise ConfigError(f"{where}.horizons_s: expected increasing positive finite times (s), got {hs}")


class IntentionForecaster(nn.Module):
    """Track (+ pose) → ``B x S x 2`` displacement at the horizons, track frame (module docstring).

    ``base`` reads the history and the speed; ``pose_residual`` (with ``cfg.pose``) reads the same plus the
    I²Former's person feature and adds to it where the track has a detected joint; ``head_yaw`` regresses the
    (cos, sin) of the head yaw relative to the track frame from the person feature (the auxiliary target).
    """

    def __init__(self, cfg: ForecasterConfig) -> None:
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        s, h = len(cfg.horizons_s), cfg.hidden
        n_in = cfg.history * 3 + 1
        self.register_buffer("horizons", torch.tensor(cfg.horizons_s, dtype=torch.float32), persistent=False)
        self.base = mlp([n_in, h, h, 2 * s], last_act=False)
        if cfg.pose:
            self.pose = I2Former(I2FormerConfig(dim=cfg.dim, heads=4, ffn_mult=2))
            self.pose_residual = mlp([n_in + cfg.dim, h, h, 2 * s], last_act=False)
            self.head_yaw = nn.Linear(cfg.dim, 2)

    def person_feature(self, kp: torch.Tensor, kp_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``B x dim`` pose features and ``B`` whether any joint was detected. The I²Former scales robot-frame
        coordinates (people up to metres away) by :data:`pretrain.i2former.POSE_SCALE_M`; in the track frame the
        joints lie within a body's size of the origin, so they are given in units of :data:`KP_SCALE_M` instead
        (without it the head's few-centimetre cues reach the attention layers as a 10⁻³ variation)."""
        kp = kp.float() * (POSE_SCALE_M / KP_SCALE_M)
        f, present = self.pose.person_features(kp[:, None], kp_mask[:, None])
        return f[:, 0], present[:, 0]

    def forward(self, b: dict[str, torch.Tensor], pose_keep: torch.Tensor | None = None,
                with_aux: bool = False) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``b``: ``hist`` B H 2, ``hist_valid`` B H, ``speed`` B, ``kp`` B 17 3, ``kp_mask`` B 17 (the pose only
        with ``cfg.pose``). ``pose_keep`` B: 0 drops a sample's pose residual (training dropout). Returns the
        ``B x S x 2`` prediction, and with ``with_aux`` also the head-yaw (cos, sin) and the has-pose mask."""
        hist = b["hist"].float()
        valid = b["hist_valid"].float()
        x = torch.cat([(hist * valid[..., None]).flatten(1), valid, b["speed"].float()[:, None]], -1)
        speed = b["speed"].float()
        cv = torch.stack([speed[:, None] * self.horizons, torch.zeros_like(speed[:, None] * self.horizons)], -1)
        out = cv + self.base(x).view(-1, len(self.cfg.horizons_s), 2)
        aux = has = None
        if self.cfg.pose:
            f, has = self.person_feature(b["kp"], b["kp_mask"])
            gate = has.float() if pose_keep is None else has.float() * pose_keep
            out = out + gate[:, None, None] * self.pose_residual(torch.cat([x, f], -1)).view_as(out)
            aux = self.head_yaw(f)
        return (out, aux, has) if with_aux else out


# ------------------------------------------------------------------------------------------- the inputs of a track
def track_frames(tracker: PedestrianTracker, rows: np.ndarray, robot_pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origins ``N x 2`` and headings ``N`` (odometry frame) of the track frames of tracks ``rows``: x along the
    estimated velocity, or along the viewing ray from the robot when the track stands."""
    pos, vel = tracker.pos[rows], tracker.vel[rows]
    speed = np.hypot(vel[:, 0], vel[:, 1])
    ray = np.arctan2(pos[:, 1] - robot_pose[1], pos[:, 0] - robot_pose[0])
    return pos, np.where(speed > STANDING_MPS, np.arctan2(vel[:, 1], vel[:, 0]), ray)


def to_track_frame(xy: np.ndarray, origin: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """Odometry-frame points ``N x ... x 2`` into the frames of ``N`` tracks (origins ``N x 2``, headings ``N``)."""
    shape = (len(origin),) + (1,) * (xy.ndim - 2)
    c, s = np.cos(heading).reshape(shape), np.sin(heading).reshape(shape)
    d = xy - origin.reshape(len(origin), *(1,) * (xy.ndim - 2), 2)
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def from_track_frame(xy: np.ndarray, origin: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """The inverse of :func:`to_track_frame`."""
    shape = (len(origin),) + (1,) * (xy.ndim - 2)
    c, s = np.cos(heading).reshape(shape), np.sin(heading).reshape(shape)
    o = origin.reshape(len(origin), *(1,) * (xy.ndim - 2), 2)
    return np.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], -1) + o


def track_inputs(tracker: PedestrianTracker, rows: np.ndarray, robot_pose: np.ndarray, poses: np.ndarray,
                 mask: np.ndarray, det_index: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """The model inputs of tracks ``rows`` after the tracker's last update, and their frames (origin, heading).

    Args:
        tracker: updated with this frame's detections.
        rows: which tracks.
        robot_pose: the robot's odometry pose (x, y, yaw) of this frame.
        poses, mask: this frame's detected keypoints ``K x 17 x 3`` (robot frame) and joints.
        det_index: for each detection the tracker was given, its row in ``poses`` (:func:`person_detections`).
    """
    origin, heading = track_frames(tracker, rows, robot_pose)
    hist = to_track_frame(tracker.hist[rows], origin, heading).astype(np.float32)
    h = tracker.history
    valid = np.arange(h)[None] >= (h - np.minimum(tracker.age[rows], h))[:, None]
    det = tracker.det[rows]
    kp = np.zeros((len(rows), N_JOINTS, 3), np.float32)
    kp_mask = np.zeros((len(rows), N_JOINTS), bool)
    seen = np.flatnonzero(det >= 0)
    if len(seen):
        k = det_index[det[seen]]
        world = robot_to_world(np.asarray(poses, np.float64)[k], robot_pose)
        kp[seen, :, :2] = to_track_frame(world[..., :2], origin[seen], heading[seen])
        kp[seen, :, 2] = world[..., 2]
        kp_mask[seen] = np.asarray(mask, bool)[k]
        kp[seen] *= kp_mask[seen][..., None]
    speed = np.hypot(tracker.vel[rows, 0], tracker.vel[rows, 1]).astype(np.float32)
    return {"hist": hist, "hist_valid": valid, "speed": speed, "kp": kp, "kp_mask": kp_mask}, origin, heading


# ------------------------------------------------------------------------------------------------ the samples
def episode_samples(ep: dict[str, np.ndarray], fps: float, horizons_s: list[float], history: int,
                    episode: int) -> dict[str, np.ndarray] | None:
    """Replays one episode through the tracker; one sample per (frame, live track matched to a true pedestrian
    whose whole horizon lies in the episode)."""
    steps = np.array([round(h * fps) for h in horizons_s])
    if np.any(steps < 1) or len(set(steps.tolist())) < len(steps):
        raise ConfigError(f"intention.model.horizons_s: {horizons_s} at {fps:g} frames/s do not give distinct "
                          "future frames")
    turn_n = round(TURN_WINDOW_S * fps)
    far = int(steps[-1])
    state = ep[PRIV_PED_STATE]  # T x N x 8: x, y, vx, vy, radius, body yaw, head yaw, present
    odom, poses, mask = ep[OBS_ODOM].astype(np.float64), ep[OBS_POSES], ep[OBS_POSE_MASK]
    t_len = len(state)
    tracker = PedestrianTracker(1.0 / fps, history=history)
    out: dict[str, list[np.ndarray]] = {}
    for t in range(t_len):
        centres, det_index = person_detections(poses[t], mask[t])
        tracker.update(robot_to_world(centres, odom[t]))
        if t + far >= t_len or not len(tracker.pos):
            continue
        present = state[t, :, 7] > 0.5
        if not present.any():
            continue
        d = np.linalg.norm(tracker.pos[:, None] - state[t, None, :, :2], axis=-1)
        d[:, ~present] = np.inf
        ped = d.argmin(1)
        ok = d[np.arange(len(ped)), ped] <= MATCH_M
        ok &= (state[t + np.arange(1, far + 1)[:, None], ped[None], 7] > 0.5).all(0)  # present all the horizon
        rows = np.flatnonzero(ok)
        if not len(rows):
            continue
        ped = ped[rows]
        x, origin, heading = track_inputs(tracker, rows, odom[t], poses[t], mask[t], det_index)
        future = state[t + steps[:, None], ped[None], :2].transpose(1, 0, 2)  # R x S x 2
        x["target"] = to_track_frame(future, origin, heading).astype(np.float32)
        kp_true = ep[PRIV_PED_KEYPOINTS][t, ped]  # R x 17 x 3, world
        x["kp_true"] = np.concatenate([to_track_frame(kp_true[..., :2], origin, heading), kp_true[..., 2:]],
                                      -1).astype(np.float32)
        yaw = wrap_angle(state[t, ped, 6] - heading)
        x["head"] = np.stack([np.cos(yaw), np.sin(yaw)], -1).astype(np.float32)
        # turn events from the true velocity over the next TURN_WINDOW_S (none counted where the window leaves the
        # episode or the pedestrian)
        win = np.minimum(t + np.arange(0, turn_n + 1), t_len - 1)
        vel = state[win[:, None], ped[None], 2:4]  # W x R x 2
        whole = (t + turn_n < t_len) & (state[win[:, None], ped[None], 7] > 0.5).all(0)
        ang = np.arctan2(vel[..., 1], vel[..., 0])
        spd = np.hypot(vel[..., 0], vel[..., 1])
        rel = wrap_angle(ang - ang[:1])
        total = rel[-1]
        turn = whole & (np.abs(total) >= math.radians(TURN_DEG)) & (spd[0] >= MIN_TURN_SPEED) & (spd[-1] >= MIN_TURN_SPEED)
        first = np.argmax(np.abs(rel) >= np.abs(total)[None] / 2, axis=0)
        x["turn"] = turn
        x["lead_s"] = np.where(turn, first / fps, np.nan).astype(np.float32)
        x["episode"] = np.full(len(rows), episode)
        x["frame"] = np.full(len(rows), t)
        x["ped"] = ped
        x["origin"], x["heading"] = origin.astype(np.float32), heading.astype(np.float32)
        for k, v in x.items():
            out.setdefault(k, []).append(v)
    return {k: np.concatenate(v) for k, v in out.items()} if out else None


def collect(root: Path, horizons_s: list[float], history: int, max_episodes: int = 0
            ) -> tuple[dict[str, np.ndarray], float, int]:
    """Every sample of a dataset (:func:`episode_samples`), its frame rate and its episode count."""
    fps = float(read_dataset_info(root).fps)
    episodes = read_episodes(root)  # names every missing column (poses, keypoints, tracks, odometry)
    if max_episodes:
        episodes = episodes[:max_episodes]
    parts = [s for e, ep in enumerate(episodes) if (s := episode_samples(ep, fps, horizons_s, history, e)) is not None]
    if not parts:
        raise InputMissingError(f"dataset {root}: no detected pedestrian is tracked with {horizons_s[-1]:g} s of "
                                "future inside its episode; the intention model has nothing to learn from")
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}, fps, len(episodes)


def take(samples: dict[str, np.ndarray], idx: np.ndarray) -> dict[str, np.ndarray]:
    return {k: v[idx] for k, v in samples.items()}


def split_samples(samples: dict[str, np.ndarray], val_fraction: float, seed: int, max_samples: int, where: str,
                  n_episodes: int, horizon_s: float
                  ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], list[int], list[int]]:
    """Training and validation samples, split by episode among the episodes that hold samples (one in which nobody
    was tracked would leave a side empty), at most ``max_samples`` training samples (seeded draw); with the
    episode lists."""
    with_samples = np.unique(samples["episode"])
    if len(with_samples) < 2:
        raise InputMissingError(f"{where}: only {len(with_samples)} of its {n_episodes} episodes hold a tracked "
                                f"pedestrian with {horizon_s:g} s of future; a training and a validation "
                                "episode are needed — record more episodes")
    tr, va = split_episodes(len(with_samples), val_fraction, seed)
    train_eps, val_eps = with_samples[tr].tolist(), with_samples[va].tolist()
    train = take(samples, np.flatnonzero(np.isin(samples["episode"], train_eps)))
    val = take(samples, np.flatnonzero(np.isin(samples["episode"], val_eps)))
    if len(train["speed"]) > max_samples:
        train = take(train, np.sort(np.random.default_rng(seed).choice(len(train["speed"]), max_samples,
                                                                       replace=False)))
    return train, val, train_eps, val_eps


# ------------------------------------------------------------------------------------------------ training
@dataclass
class FitOptions:
    epochs: int
    batch: int
    lr: float
    pose_dropout: float
    head_aux_weight: float
    seed: int


KP_SOURCES = ("detected", "true", "centroid")


def _batch(s: dict[str, np.ndarray], idx: np.ndarray, device: torch.device, kp_source: str = "detected"
           ) -> dict[str, torch.Tensor]:
    """A batch of samples ``idx``; ``kp_source``: the detected keypoints, the simulator's (all joints), or every
    detected joint moved to the detected joints' mean (the pose's position without its shape)."""
    b = {k: torch.from_numpy(s[k][idx]).to(device) for k in ("hist", "hist_valid", "speed", "target", "head")}
    if kp_source == "true":
        b["kp"] = torch.from_numpy(s["kp_true"][idx]).to(device)
        b["kp_mask"] = torch.ones(len(idx), N_JOINTS, dtype=torch.bool, device=device)
        return b
    kp, mask = s["kp"][idx], s["kp_mask"][idx]
    if kp_source == "centroid":
        n = np.maximum(mask.sum(-1, keepdims=True), 1)[..., None]
        kp = np.where(mask[..., None], (kp * mask[..., None]).sum(1, keepdims=True) / n, 0.0).astype(np.float32)
    b["kp"], b["kp_mask"] = torch.from_numpy(kp).to(device), torch.from_numpy(mask).to(device)
    return b


def fit_model(model: IntentionForecaster, train: dict[str, np.ndarray], val: dict[str, np.ndarray], opt: FitOptions,
              device: torch.device, kp_source: str = "detected", log_rows: list[dict] | None = None,
              name: str = "") -> IntentionForecaster:
    """Trains ``model`` on ``train`` (mean displacement error over the horizons + the head-yaw auxiliary loss)."""
    torch.manual_seed(opt.seed)
    model.to(device).train()
    optim = torch.optim.AdamW(model.parameters(), lr=opt.lr, weight_decay=1e-4)
    n = len(train["speed"])
    steps = math.ceil(n / opt.batch)
    sched = one_cycle(optim, opt.lr, opt.epochs * steps)
    gen = np.random.default_rng(opt.seed)
    for epoch in range(opt.epochs):
        order = gen.permutation(n)
        total = 0.0
        for i in range(steps):
            idx = order[i * opt.batch:(i + 1) * opt.batch]
            b = _batch(train, idx, device, kp_source)
            keep = None
            if model.cfg.pose and opt.pose_dropout > 0:
                keep = (torch.rand(len(idx), generator=None, device=device) >= opt.pose_dropout).float()
            pred, aux, has = model(b, keep, with_aux=True)
            loss = (pred - b["target"]).norm(dim=-1).mean()
            if aux is not None and opt.head_aux_weight > 0 and bool(has.any()):
                loss = loss + opt.head_aux_weight * ((aux - b["head"]) ** 2).sum(-1)[has].mean()
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
            sched.step()
            total += float(loss.detach()) * len(idx)
        if log_rows is not None:
            last = predict(model, val, device, kp_source)[:, -1] - val["target"][:, -1]
            fde = float(np.linalg.norm(last, axis=-1).mean())
            model.train()
            log_rows.append({"model": name, "epoch": epoch + 1, "train_loss": round(total / n, 5),
                             "val_fde_last_m": round(fde, 5)})
    return model.eval()


@torch.no_grad()
def predict(model: IntentionForecaster | None, s: dict[str, np.ndarray], device: torch.device | str = "cpu",
            kp_source: str = "detected", batch: int = 8192, horizons_s: list[float] | None = None) -> np.ndarray:
    """``N x S x 2`` predictions (track frame); ``model=None`` is constant velocity at ``horizons_s``."""
    if model is None:
        h = np.asarray(horizons_s, np.float32)
        return np.stack([s["speed"][:, None] * h, np.zeros((len(s["speed"]), len(h)), np.float32)], -1)
    model.eval()
    n = len(s["speed"])
    return np.concatenate([model(_batch(s, np.arange(i, min(i + batch, n)), torch.device(device), kp_source)).cpu()
                           .numpy() for i in range(0, n, batch)])


# ------------------------------------------------------------------------------------------------ evaluation
def _groups(s: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    g = {"all": np.ones(len(s["speed"]), bool), "turns": s["turn"].astype(bool),
         "with_pose": s["kp_mask"].any(-1), "turns_with_pose": s["turn"].astype(bool) & s["kp_mask"].any(-1)}
    for lo, hi in LEAD_BINS_S:
        g[f"turns_lead_{lo:g}-{min(hi, TURN_WINDOW_S):g}s"] = g["turns"] & (s["lead_s"] > lo) & (s["lead_s"] <= hi)
    return g


def evaluate(preds: dict[str, np.ndarray], s: dict[str, np.ndarray], horizons_s: list[float], n_boot: int,
             seed: int) -> dict[str, Any]:
    """ADE / FDE@1 s / FDE@last per model and group, and bootstrap intervals (resampling validation episodes) of
    the FDE@1 s differences that decide the question: pose − position, pose − cv, position − cv."""
    i1 = int(np.argmin(np.abs(np.asarray(horizons_s) - 1.0)))
    err = {m: np.linalg.norm(p - s["target"], axis=-1) for m, p in preds.items()}  # N x S
    groups = _groups(s)
    res: dict[str, Any] = {m: {} for m in preds}
    for m, e in err.items():
        for g, sel in groups.items():
            res[m][g] = {"n": int(sel.sum()), "ade_m": float(e[sel].mean()) if sel.any() else float("nan"),
                         "fde_1s_m": float(e[sel, i1].mean()) if sel.any() else float("nan"),
                         f"fde_{horizons_s[-1]:g}s_m": float(e[sel, -1].mean()) if sel.any() else float("nan")}
    eps = np.unique(s["episode"])
    rng = np.random.default_rng(seed)
    by_ep = {e: np.flatnonzero(s["episode"] == e) for e in eps}
    pairs = [(a, b) for a, b in (("pose", "position"), ("pose", "cv"), ("position", "cv"), ("pose", "pose_centroid"),
                                 ("pose_true", "position"))
             if a in err and b in err]
    boot: dict[str, Any] = {}
    for g in ("all", "turns", "turns_with_pose"):
        sel = groups[g]
        if not sel.any():
            continue
        for a, b in pairs:
            diffs = []
            for _ in range(n_boot):
                idx = np.concatenate([by_ep[e] for e in rng.choice(eps, len(eps))])
                idx = idx[sel[idx]]
                if len(idx):
                    diffs.append(float((err[a][idx, i1] - err[b][idx, i1]).mean()))
            point = float((err[a][sel, i1] - err[b][sel, i1]).mean())
            base = float(err[b][sel, i1].mean())
            lo, hi = (np.percentile(diffs, [2.5, 97.5]).tolist() if diffs else [float("nan")] * 2)
            boot[f"{g}:{a}-{b}"] = {"fde_1s_diff_m": point, "ci95_m": [lo, hi],
                                    "relative": point / base if base > 0 else float("nan")}
    return {"results": res, "differences_fde_1s": boot, "fde_1s_horizon_s": horizons_s[i1]}


def _num(v: float | None, spec: str) -> str:
    """A number for the tables; an empty group (NaN, written as null) as a dash."""
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def markdown(metrics: dict) -> str:
    res = metrics["results"]
    groups = list(res["cv"])
    last = [k for k in res["cv"]["all"] if k.startswith("fde_") and k != "fde_1s_m"][0]
    lines = [f"FDE at 1 s / {last[4:-2]} (ADE), m — validation episodes {metrics['episodes']['val']}, "
             f"samples {metrics['samples']['val']}", "",
             "| model | " + " | ".join(f"{g} [n={res['cv'][g]['n']}]" for g in groups) + " |",
             "|" + "---|" * (len(groups) + 1)]
    for m, r in res.items():
        lines.append(f"| {m} | " + " | ".join(
            f"{_num(r[g]['fde_1s_m'], '.3f')} / {_num(r[g][last], '.3f')} ({_num(r[g]['ade_m'], '.3f')})"
            for g in groups) + " |")
    lines += ["", "| FDE@1 s difference | m | 95 % bootstrap (episodes) | relative |", "|---|---|---|---|"]
    for k, d in metrics["differences_fde_1s"].items():
        lo, hi = d["ci95_m"]
        lines.append(f"| {k} | {_num(d['fde_1s_diff_m'], '+.3f')} | [{_num(lo, '+.3f')}, {_num(hi, '+.3f')}] | "
                     f"{_num(d['relative'], '+.1%')} |")
    return "\n".join(lines) + "\n"


def plot_errors(path: Path, metrics: dict) -> None:
    plot_model_errors(path, metrics["results"], "fde_1s_m", "FDE at +1.0 s (m)",
                      "Tracked pedestrians 1 s ahead, validation episodes: constant velocity, track, + detected pose, "
                      "+ centroid, + true pose")


def plot_turn(path: Path, s: dict[str, np.ndarray], i: int, preds: dict[str, np.ndarray]) -> None:
    """One turning pedestrian: its track history, the true future and each model's prediction (track frame)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    h = s["hist"][i][s["hist_valid"][i]]
    ax.plot(h[:, 0], h[:, 1], "k.-", label="track (past)")
    ax.plot(*np.r_[[[0, 0]], s["target"][i]].T, "k-", lw=2.5, alpha=0.5, label="true future")
    for m, p in preds.items():
        ax.plot(*np.r_[[[0, 0]], p[i]].T, ".-", label=m)
    kp, km = s["kp"][i], s["kp_mask"][i]
    if km.any():
        ax.scatter(kp[km, 0], kp[km, 1], s=8, c="m", label="detected joints")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x along the track's velocity (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"episode {int(s['episode'][i])}, frame {int(s['frame'][i])}, turn {s['lead_s'][i]:.1f} s ahead",
                 fontsize=8)
    ax.legend(fontsize=6, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------ the stage
@dataclass
class IntentionConfig(BaseStageConfig):
    """Config of the ``pretrain-intention`` stage."""
    PLACEMENT_FIELDS: ClassVar[tuple[str, ...]] = ("threads",)  # how many cores, as device says where

    repo_id: str = "icrowdnav/expert"  # dataset: DATA_DIR/datasets/<repo_id>/
    name: str = "intention"  # output: DATA_DIR/checkpoints/<name>/
    model: ForecasterConfig = field(default_factory=ForecasterConfig)
    epochs: int = 12
    batch: int = 256
    lr: float = 3e-3  # AdamW peak learning rate (one-cycle)
    pose_dropout: float = 0.3  # fraction of training samples whose pose residual is dropped
    head_aux_weight: float = 0.2  # weight of the head-yaw auxiliary loss
    val_fraction: float = 0.1  # validation episodes, split by episode among those that hold samples
    max_episodes: int = 0  # use at most this many episodes (0 = all)
    max_samples: int = 300_000  # training samples drawn at most (seeded)
    ceiling: bool = True  # also fit and report the references (true keypoints: the ceiling; the detected joints'
    # centroid: what the pose adds beyond a fresher position) — evaluated, not saved
    bootstrap: int = 1000  # bootstrap resamples of the validation episodes
    figures: int = 3  # turning pedestrians drawn
    threads: int = 0  # torch CPU threads (0 = every core)
    device: str = "auto"  # auto | cpu | cuda | cuda:N (not in the config hash)

    def validate(self) -> None:
        super().validate()
        check_run_name(self.name)
        self.model.validate()
        if not self.model.pose:
            raise ConfigError("pretrain-intention.model.pose: expected true (the saved forecaster reads the pose; the "
                              "position-only model is fitted beside it)")
        for k, lo in (("epochs", 1), ("batch", 1), ("max_samples", 100), ("bootstrap", 0), ("figures", 0),
                      ("threads", 0), ("max_episodes", 0)):
            if getattr(self, k) < lo:
                raise ConfigError(f"pretrain-intention.{k}: expected an integer >= {lo}, got {getattr(self, k)}")
        for k in ("lr", "pose_dropout", "head_aux_weight", "val_fraction"):
            if not math.isfinite(getattr(self, k)):
                raise ConfigError(f"pretrain-intention.{k}: expected a finite number, got {getattr(self, k)}")
        if not (self.lr > 0 and 0 <= self.pose_dropout < 1 and self.head_aux_weight >= 0 and 0 < self.val_fraction < 1):
            raise ConfigError("pretrain-intention: expected lr > 0, 0 <= pose_dropout < 1, head_aux_weight >= 0, "
                              f"0 < val_fraction < 1, got {self.lr}, {self.pose_dropout}, {self.head_aux_weight}, "
                              f"{self.val_fraction}")
        resolve_device(self.device, "pretrain-intention.device")


def dataset_dir(cfg: IntentionConfig) -> Path:
    return layout.dataset_dir(cfg.data_dir, cfg.repo_id)


def checkpoint_dir(cfg: IntentionConfig) -> Path:
    return layout.checkpoint_dir(cfg.data_dir, cfg.name)


def inputs(cfg: IntentionConfig) -> list[Path]:
    root = dataset_dir(cfg)
    read_dataset_info(root)  # a missing or old-format dataset: one named error before anything is written
    return [root / "meta", root / "data"]  # the parquet files only: no video is read


def body(cfg: IntentionConfig, out: Path) -> dict:
    t0 = time.monotonic()
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    device = resolve_device(cfg.device, "pretrain-intention.device")
    root = dataset_dir(cfg)
    mc = cfg.model
    samples, fps, n_eps = collect(root, mc.horizons_s, mc.history, cfg.max_episodes)
    train, val, train_eps, val_eps = split_samples(samples, cfg.val_fraction, cfg.seed, cfg.max_samples,
                                                   f"dataset {root}", n_eps, mc.horizons_s[-1])
    log.info("pretrain-intention: %d training / %d validation samples (%d / %d turn events) from %d episodes on %s",
             len(train["speed"]), len(val["speed"]), int(train["turn"].sum()), int(val["turn"].sum()), n_eps, device)
    opt = FitOptions(cfg.epochs, cfg.batch, cfg.lr, cfg.pose_dropout, cfg.head_aux_weight, cfg.seed)
    rows: list[dict] = []
    seconds: dict[str, float] = {}
    models: dict[str, IntentionForecaster] = {}
    preds = {"cv": predict(None, val, horizons_s=mc.horizons_s)}
    for name, source in MODELS.items():
        if name in ("pose_true", "pose_centroid") and not cfg.ceiling:
            continue
        t = time.monotonic()
        m = IntentionForecaster(ForecasterConfig(**{**asdict(mc), "pose": source is not None}))
        models[name] = fit_model(m, train, val, opt, device, kp_source=source or "detected", log_rows=rows, name=name)
        preds[name] = predict(models[name], val, device, kp_source=source or "detected")
        seconds[name] = round(time.monotonic() - t, 1)
        log.info("pretrain-intention: %-9s fitted in %.0f s", name, seconds[name])
    metrics = evaluate(preds, val, mc.horizons_s, cfg.bootstrap, cfg.seed)
    with_pose = float(val["kp_mask"].any(-1).mean())
    metrics.update({
        "episodes": {"train": len(train_eps), "val": len(val_eps)},
        "samples": {"train": len(train["speed"]), "val": len(val["speed"]), "val_turns": int(val["turn"].sum()),
                    "val_with_pose": with_pose},
        "definitions": {"frame": "track frame: origin at the track, x along its estimated velocity (or the viewing "
                                 f"ray when slower than {STANDING_MPS:.1f} m/s)",
                        "target": f"true position of the pedestrian nearest the track (<= {MATCH_M:.1f} m) at each "
                                  "horizon",
                        "turn": f"true walking direction turns >= {TURN_DEG:g} deg within {TURN_WINDOW_S:g} s",
                        "bootstrap": f"{cfg.bootstrap} resamples of the validation episodes, 95 % percentile"},
        "model_seconds": seconds, "seconds": round(time.monotonic() - t0, 1), **device_counts(device)})
    metrics = json_safe(metrics)
    write_forecaster_checkpoint(out, models["pose"], models["position"], fps, {
        "repo_id": cfg.repo_id, "train_episodes": train_eps, "val_episodes": val_eps})
    atomic_write_json(out / METRICS_JSON, metrics)
    atomic_write_text(out / "metrics.md", markdown(metrics))
    with open(out / "train_log.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["model", "epoch", "train_loss", "val_fde_last_m"])
        w.writeheader()
        w.writerows(rows)
    (out / "figures").mkdir(exist_ok=True)
    plot_errors(out / "figures" / "errors.png", metrics)
    turns = np.flatnonzero(val["turn"] & val["kp_mask"].any(-1) & (val["lead_s"] > 0.3))
    picks = turns[np.linspace(0, len(turns) - 1, cfg.figures).astype(int)] if len(turns) and cfg.figures else []
    for k, i in enumerate(picks):
        plot_turn(out / "figures" / f"turn_{k}.png", val, int(i), {m: p for m, p in preds.items()})
    r = metrics["results"]
    counts = {"train_samples": len(train["speed"]), "val_samples": len(val["speed"]), "episodes": n_eps,
              **device_counts(device)}
    for m in r:
        counts[f"fde_1s_{m}_m"] = round(r[m]["all"]["fde_1s_m"], 4)
        counts[f"fde_1s_turns_{m}_m"] = round(r[m]["turns"]["fde_1s_m"], 4)
    log.info("pretrain-intention: FDE@1 s on turn events: %s", ", ".join(f"{m} {r[m]['turns']['fde_1s_m']:.3f} m"
                                                                         for m in r))
    return counts


# ------------------------------------------------------------------------------------------------ the checkpoint
def write_forecaster_checkpoint(out: Path, pose: IntentionForecaster, position: IntentionForecaster, fps: float,
                                dataset: dict[str, Any], **extra: Any) -> None:
    """Writes ``forecaster.safetensors``, ``position.safetensors`` and, last, ``intention.json`` (with ``extra``)
    into ``out`` (the stage runner adds ``config.yaml`` and ``manifest.json``)."""
    out.mkdir(parents=True, exist_ok=True)
    meta = {"format_version": str(FORMAT_VERSION)}
    save_safetensors(pose.cpu(), out / FORECASTER_WEIGHTS, meta)
    save_safetensors(position.cpu(), out / POSITION_WEIGHTS, meta)
    desc = {"format_version": FORMAT_VERSION, "model": {**asdict(pose.cfg), "pose": True}, "fps": fps,
            "files": {FORECASTER_WEIGHTS: "pose (detected keypoints)", POSITION_WEIGHTS: "position only"},
            "dataset": dataset, **extra}
    atomic_write_text(out / INTENTION_JSON, json.dumps(desc, indent=2, sort_keys=True) + "\n")


def _json_or_empty(path: Path) -> dict[str, Any]:
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return d if isinstance(d, dict) else {}


def load_forecaster(ckpt: Path, which: str = "pose") -> tuple[IntentionForecaster, dict[str, Any]]:
    """The frozen intention model of a finished checkpoint (``which``: ``pose`` or ``position``) and its
    ``intention.json``.

    Raises:
        InputMissingError: no or unfinished checkpoint. CorruptArtifactError: unreadable or mismatching files.
    """
    ckpt = Path(ckpt)
    if not ckpt.is_dir():
        raise InputMissingError(f"no intention checkpoint at {ckpt}; make one with `make pretrain` "
                                "(icrowdnav pretrain-intention)")
    path = ckpt / INTENTION_JSON
    if not (ckpt / MANIFEST_NAME).is_file() and TUNED_FROM not in _json_or_empty(path):
        # a fine-tuned one (finetune_forecaster) lives inside a policy checkpoint: complete once intention.json exists
        raise InputMissingError(f"intention checkpoint {ckpt} is unfinished (no {MANIFEST_NAME}); redo it with "
                                "`icrowdnav pretrain-intention --overwrite`")
    try:
        desc = json.loads(path.read_text())
        cfg = ForecasterConfig(**{**desc["model"], "pose": which == "pose"})
    except FileNotFoundError:
        raise InputMissingError(f"intention checkpoint {ckpt} has no {INTENTION_JSON}") from None
    except (json.JSONDecodeError, KeyError, TypeError, UnicodeDecodeError) as e:
        raise CorruptArtifactError(f"corrupt {path}: {type(e).__name__}: {e}") from None
    if desc.get("format_version") != FORMAT_VERSION:
        raise CorruptArtifactError(f"{path}: format_version {desc.get('format_version')!r}, expected {FORMAT_VERSION}")
    if which not in ("pose", "position"):
        raise ConfigError(f"intention model: expected 'pose' or 'position', got {which!r}")
    try:
        cfg.validate(str(path))
    except ConfigError as e:
        raise CorruptArtifactError(str(e)) from None
    model = IntentionForecaster(cfg)
    load_safetensors(model, ckpt / (FORECASTER_WEIGHTS if which == "pose" else POSITION_WEIGHTS))
    model.eval().requires_grad_(False)
    return model, desc


# ------------------------------------------------------------------------------------------------ fine-tuning
def _collect_many(roots: list[Path], horizons_s: list[float], history: int) -> tuple[dict[str, np.ndarray], float, int]:
    """:func:`collect` over several datasets, episode ids made unique (offset by the episodes before them)."""
    parts, fps, offset = [], 0.0, 0
    for root in roots:
        try:
            s, fps, n = collect(root, horizons_s, history)
        except InputMissingError:  # a dataset in which nobody was tracked long enough adds nothing
            n = len(read_episodes(root))
        else:
            parts.append({**s, "episode": s["episode"] + offset})
        offset += n
    if not parts:
        raise InputMissingError(f"datasets {[str(r) for r in roots]}: no detected pedestrian is tracked with "
                                f"{horizons_s[-1]:g} s of future; the intention model has nothing to fine-tune on")
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}, fps, offset


def finetune_forecaster(pretrained: Path, roots: list[Path], out: Path, opt: FitOptions, val_fraction: float,
                        device: torch.device | str = "cpu") -> dict[str, Any]:
    """Fine-tunes the pretrained pose forecaster of ``pretrained`` on the datasets ``roots`` (a student's own DAgger
    rollouts: the people as they move around *that* robot) and writes it to ``out`` — a checkpoint
    :func:`load_forecaster` reads (``intention.json`` names ``tuned_from``; the position-only model is copied
    unchanged). Starts from the pretrained weights every time (a resumed or repeated call gives the same model).

    Returns the validation errors (episodes split off ``roots`` by ``opt.seed``) of constant velocity, the pretrained
    and the fine-tuned model — FDE@1 s over all samples and over turn events, with the counts — so whether the
    fine-tuning helped is measured where it is used."""
    device = torch.device(device)
    (Path(out) / INTENTION_JSON).unlink(missing_ok=True)  # written last: until then ``out`` is not a checkpoint
    model, desc = load_forecaster(pretrained)
    position, _ = load_forecaster(pretrained, "position")
    hz, history = desc["model"]["horizons_s"], desc["model"]["history"]
    samples, fps, n_eps = _collect_many(roots, hz, history)
    if abs(fps - float(desc["fps"])) > 1e-6:
        raise ConfigError(f"intention fine-tuning: the datasets run at {fps:g} frames/s, the pretrained model "
                          f"{pretrained} at {desc['fps']:g}")
    train, val, train_eps, val_eps = split_samples(samples, val_fraction, opt.seed, len(samples["speed"]),
                                                   f"datasets {[str(r) for r in roots]}", n_eps, hz[-1])
    before = predict(model, val, device)
    model.requires_grad_(True)
    t = time.monotonic()
    fit_model(model, train, val, opt, device)
    model.requires_grad_(False)
    preds = {"cv": predict(None, val, horizons_s=hz), "pretrained": before, "tuned": predict(model, val, device)}
    res = evaluate(preds, val, hz, n_boot=0, seed=opt.seed)["results"]
    errors = {name: {key: None if math.isnan(r[group]["fde_1s_m"]) else round(r[group]["fde_1s_m"], 4)
                     for key, group in (("fde_1s_m", "all"), ("fde_1s_turns_m", "turns"))} for name, r in res.items()}
    result = {"train_samples": len(train["speed"]), "val_samples": len(val["speed"]),
              "val_turns": int(val["turn"].astype(bool).sum()),
              "train_episodes": len(train_eps), "val_episodes": len(val_eps), "epochs": opt.epochs, "lr": opt.lr,
              "seconds": round(time.monotonic() - t, 1), "val": errors}
    write_forecaster_checkpoint(Path(out), model, position, fps,
                                {"roots": [str(r) for r in roots], "train_episodes": train_eps,
                                 "val_episodes": val_eps}, **{TUNED_FROM: str(pretrained), "tuning": result})
    return result
