"""What a trained ViNT-style checkpoint has learned, measured offline on its dataset's frames.

The closed-loop benchmark says only *that* ViNT-style fails; this says *what* it predicts. On the frames of one split
(the training's own validation episodes by default, or its training episodes) it reports:

* per waypoint component (Δx, Δy, cos, sin of the relative yaw; all ``H`` waypoints) the model's mean squared error
  against the split's **mean predictor** (the label's per-waypoint mean): an R² ≤ 0 means the network predicts that
  component no better than a constant;
* the steering the controller would derive — ω = atan(Δy / Δx) / DT of the followed waypoint, before the robot's
  limits clip it (:func:`rl.baselines.vint.driver.vint_controller`) — from the predicted and from the label
  waypoints, each correlated with the expert's recorded ω (``action``);
* the goal's influence: the mean change of the followed waypoint's Δy when the goal's bearing is mirrored, against
  the spread of that prediction over the split;
* the signal the labels hold: the R² of a least-squares probe of the followed waypoint's Δy from the goal features,
  from the robot's own past motion (yaw change and distance over the last ``spacing`` frames, from odometry — which
  ViNT never sees, but its context images show it), and from both; always fitted on the training episodes and
  scored on the validation episodes, whichever split the model is scored on.

::

    python -m rl.baselines.vint.diagnose data/checkpoints/policy/vint [--dataset ROOT] [--split val|train]
        [--seed 0] [--val-fraction 0.1] [--out diag.json]

The split is :func:`pretrain.data.split_episodes` with the training's seed and ``val_fraction`` (the defaults are
the default profile's); a split whose size differs from the checkpoint's ``produced_by.val_episodes`` is an error.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.core.artifacts import atomic_write_json
from pipeline.core.errors import ConfigError, CorruptArtifactError, reports_errors
from pretrain.data import split_episodes
from rl.baselines.common import load_baseline
from rl.baselines.vint.configuration import NAME, Config
from rl.baselines.vint.data import Frames, load_dataset
from rl.baselines.vint.driver import vint_controller
from rl.baselines.vint.model import ViNTStyle, build_model
from rl.baselines.vint.training import Trainer, groups

COMPONENTS = ("dx", "dy", "cos", "sin")


def predict(model: ViNTStyle, trainer: Trainer, episodes: list[int]
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(predicted waypoints, the same with the goal's bearing mirrored — its sin feature negated, nothing else —,
    label waypoints, target frame indices) over every frame of ``episodes``, in order; the images are encoded once
    for both predictions."""
    preds, mirrored, labels, targets = [], [], [], []
    flip = torch.tensor([1.0, -1.0, 1.0])
    model.eval()
    with torch.no_grad():
        for group in groups(trainer.clips(episodes, None), trainer.cfg.clips_per_batch):
            t = np.concatenate(group)
            b = trainer.batch(t, mirror=False)
            tokens = model.encode(b.frames)[b.window]
            preds.append(model.head(tokens, b.goal)[1].numpy())
            mirrored.append(model.head(tokens, b.goal * flip)[1].numpy())
            labels.append(b.waypoints.numpy())
            targets.append(t)
    return tuple(np.concatenate(x) for x in (preds, mirrored, labels, targets))


def _omega(wp: np.ndarray, index: int, metres_per_step: float, dt_s: float) -> np.ndarray:
    """The controller's ω for each frame's waypoint ``index``, without the robot's limits."""
    out = np.empty(len(wp))
    for i, w in enumerate(wp[:, index]):
        m = np.array([w[0] * metres_per_step, w[1] * metres_per_step, w[2], w[3]])
        out[i] = vint_controller(m, dt_s, math.inf, math.inf)[1]
    return out


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else 0.0


def probe_features(frames: Frames, targets: np.ndarray, goal: np.ndarray, spacing: int) -> dict[str, np.ndarray]:
    """The probes' inputs per target frame: ``goal`` (the model's goal features), ``motion`` (yaw change and distance
    over the last ``spacing`` frames, the episode's first frame held before its start), ``both``."""
    start, _ = frames.bounds()
    prev = np.maximum(targets - spacing, start[targets])
    dyaw = np.angle(np.exp(1j * (frames.pose[targets, 2] - frames.pose[prev, 2])))
    dist = np.hypot(*(frames.pose[targets, :2] - frames.pose[prev, :2]).T)
    motion = np.stack([dyaw, dist], -1)
    return {"goal": goal, "motion": motion, "both": np.concatenate([goal, motion], -1)}


def probe_r2(x_fit: np.ndarray, y_fit: np.ndarray, x: np.ndarray, y: np.ndarray) -> float:
    """R² on (``x``, ``y``) of the least-squares affine fit on (``x_fit``, ``y_fit``)."""
    w, *_ = np.linalg.lstsq(np.c_[x_fit, np.ones(len(x_fit))], y_fit, rcond=None)
    resid = y - np.c_[x, np.ones(len(x))] @ w
    return float(1.0 - resid.var() / max(y.var(), 1e-12))


def diagnose(model: ViNTStyle, deploy: dict[str, Any], frames: Frames, episodes: list[int],
             probe_fit: list[int], probe_score: list[int]) -> dict[str, Any]:
    """The module docstring's figures: the model's on the frames of ``episodes``, the probes fitted on the frames
    of ``probe_fit`` and scored on those of ``probe_score``."""
    if frames.action is None:
        raise ConfigError("vint diagnose: the frames carry no expert action (load them with load_dataset)")
    cfg = replace(Config(), context=model.context, horizon=model.horizon, spacing=int(deploy["spacing"]),
                  image_hw=list(model.image_hw), goal_scale_m=float(deploy["goal_scale_m"]),
                  max_dist=int(deploy["max_dist"]))
    mps, k = float(deploy["metres_per_step"]), int(deploy["waypoint_index"])
    dt_s = cfg.spacing / float(deploy["fps"])
    trainer = Trainer(frames, cfg, mps)
    pred, mirrored, label, targets = predict(model, trainer, episodes)
    out: dict[str, Any] = {"frames": int(len(targets)), "episodes": len(episodes), "components": {}}
    for i, name in enumerate(COMPONENTS):
        mse = float(((pred[..., i] - label[..., i]) ** 2).mean())
        const = float(((label[..., i] - label[..., i].mean(0)) ** 2).mean())
        out["components"][name] = {"mse": mse, "mean_predictor_mse": const, "r2": 1.0 - mse / max(const, 1e-12)}
    w_expert = frames.action[targets, 1]
    out["omega_corr_predicted"] = _corr(_omega(pred, k, mps, dt_s), w_expert)
    out["omega_corr_label"] = _corr(_omega(label, k, mps, dt_s), w_expert)
    out["goal_mirror_dy_change"] = float(np.abs(mirrored[:, k, 1] - pred[:, k, 1]).mean())
    out["predicted_dy_std"] = float(pred[:, k, 1].std())
    out["label_dy_std"] = float(label[:, k, 1].std())
    (x_fit, y_fit), (x, y) = (probe_data(trainer, eps, k) for eps in (probe_fit, probe_score))
    out["probe_r2_dy"] = {name: probe_r2(x_fit[name], y_fit, x[name], y) for name in x}
    return out


def probe_data(trainer: Trainer, episodes: list[int], k: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The probes' inputs (:func:`probe_features`) and label (waypoint ``k``'s Δy) on every frame of ``episodes``
    (no network)."""
    t = np.concatenate(trainer.clips(episodes, None))
    b = trainer.batch(t, mirror=False)
    return probe_features(trainer.frames, t, b.goal.numpy(), trainer.cfg.spacing), b.waypoints.numpy()[:, k, 1]


def report(d: dict[str, Any]) -> str:
    """The figures as a few lines of text."""
    lines = [f"{d['frames']} frames of {d['episodes']} episodes ({d['split']} split)",
             "component  model MSE  mean-predictor MSE  R²"]
    lines += [f"{n:9s}  {c['mse']:9.4f}  {c['mean_predictor_mse']:18.4f}  {c['r2']:+.3f}"
              for n, c in d["components"].items()]
    lines.append(f"controller ω vs the expert's ω: correlation {d['omega_corr_predicted']:+.3f} from the predicted "
                 f"waypoint, {d['omega_corr_label']:+.3f} from the label waypoint")
    lines.append(f"goal bearing mirrored: the followed waypoint's Δy changes by {d['goal_mirror_dy_change']:.4f} "
                 f"(its spread over the frames {d['predicted_dy_std']:.4f}; the labels' {d['label_dy_std']:.4f})")
    p = d["probe_r2_dy"]
    lines.append(f"linear probes of that Δy label (fitted on the training episodes), R² on the validation ones: goal {p['goal']:+.3f}, past motion {p['motion']:+.3f}, "
                 f"both {p['both']:+.3f}")
    return "\n".join(lines)


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rl.baselines.vint.diagnose", description=__doc__.split("\n")[0])
    ap.add_argument("ckpt", type=Path, help="a ViNT-style checkpoint directory (policy.json + weights)")
    ap.add_argument("--dataset", type=Path, help="its LeRobot dataset (default: the one policy.json names)")
    ap.add_argument("--split", choices=("val", "train"), default="val")
    ap.add_argument("--seed", type=int, default=0, help="the training's seed (its episode split)")
    ap.add_argument("--val-fraction", type=float, default=Config().val_fraction)
    ap.add_argument("--out", type=Path, help="also write the figures as JSON")
    a = ap.parse_args(argv)
    model, desc = load_baseline(a.ckpt, NAME, build_model)
    budget = desc.get("produced_by") or {}
    root = a.dataset or (Path(budget["dataset"]) if budget.get("dataset") else None)
    if root is None:
        raise ConfigError(f"{a.ckpt / 'policy.json'}: produced_by names no dataset; pass --dataset")
    try:
        deploy = desc["deploy"]
    except KeyError:
        raise CorruptArtifactError(f"{a.ckpt / 'policy.json'}: no deploy block") from None
    frames, _ = load_dataset(root, list(model.image_hw), int(budget.get("episodes") or 0), progress=False)
    train_eps, val_eps = split_episodes(len(frames.slices), a.val_fraction, a.seed)
    if budget.get("val_episodes") is not None and int(budget["val_episodes"]) != len(val_eps):
        raise ConfigError(f"--val-fraction {a.val_fraction}: expected the checkpoint's split of "
                          f"{budget['val_episodes']} validation episodes, got {len(val_eps)}")
    eps = val_eps if a.split == "val" else train_eps
    d = {"checkpoint": str(a.ckpt), "dataset": str(root), "split": a.split, "seed": a.seed,
         **diagnose(model, deploy, frames, eps, train_eps, val_eps)}
    print(report(d))
    if a.out:
        atomic_write_json(a.out, d)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
