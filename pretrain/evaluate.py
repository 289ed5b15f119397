"""Evaluate a pretrained BEV encoder on a dataset: IoU per pretext target at several decision thresholds.

::

    python -m pretrain.evaluate data/checkpoints/bev                          # its own validation episodes
    python -m pretrain.evaluate data/checkpoints/bev --dataset data/datasets/icrowdnav/other --episodes all
    python -m pretrain.evaluate data/checkpoints/bev --episodes 0,5,9 --out eval.json

The checkpoint carries its grid and cameras (``encoder.json``); the dataset's cameras must be the same (an
encoder lifts with the intrinsics/extrinsics it was trained with). IoU is dataset-level over the chosen frames,
cells in the cameras' field of view only, at each threshold on the heads' probabilities; 0.5 is the headline
figure of ``metrics.json``. Thresholds can be *chosen* on training episodes (``--episodes train``) and then
applied to validation ones — choosing them on the validation episodes and reporting the same episodes is
optimistic.

``visible_people`` asks how much of the "pedestrians now" error is occlusion: the label marks every person in the
field of view, also those behind the first row whom no depth ray reaches. A person counts as *seen* when at least
one of the frame's measured depth points in the height band falls on its disc — the rule of the ``seen`` people
label (:func:`pretrain.data.seen_people`, one definition for training and scoring); the cells of unseen people are
left out of the IoU (neither a miss nor a false alarm), which gives the IoU a camera-only model could reach on the
people it can see. Reported beside the plain
IoU at the same thresholds, with the share of label cells that belong to unseen people.

``--region outside`` scores the grid's cells *outside* the cameras' field of view instead — where the training
loss never reaches (:func:`pretrain.train.masked_bce` is restricted to the view), so what the heads say there is
the encoder's extrapolation, which a student's map cost still reads. ``rates`` gives, per target and over the
region's cells of valid frames, the mean predicted probability where the label is empty and where it is occupied,
and the label's occupied share: a calibration gauge (a head that knew nothing there would say the occupied share
everywhere).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from pipeline.core.artifacts import atomic_write_json
from pipeline.core.errors import ConfigError, reports_errors
from pretrain.checkpoint import load_encoder, load_heads, read_encoder_json
from pretrain.data import PEOPLE_LABELS, check_dataset, load_frames, make_batches, make_clips
from pretrain.geometry import check_grid_fits_cameras
from pretrain.model import TARGETS
from pretrain.train import forward_batch, iou_counts

PEOPLE_NOW = TARGETS.index("ped_t")

THRESHOLDS = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
REGIONS = ("fov", "outside")  # the cells scored: in the cameras' field of view, or the rest of the grid


def check_same_cameras(encoder_cams, dataset_cams, where: str) -> None:
    """The dataset must have the encoder's cameras (names, sizes, K, T_base_cam)."""
    if [c.name for c in encoder_cams] != [c.name for c in dataset_cams]:
        raise ConfigError(f"{where}: cameras {[c.name for c in dataset_cams]} differ from the encoder's "
                          f"{[c.name for c in encoder_cams]}")
    for a, b in zip(encoder_cams, dataset_cams, strict=True):
        if (a.width, a.height) != (b.width, b.height) or not (np.allclose(a.K_np, b.K_np, atol=1e-6)
                                                             and np.allclose(a.T_np, b.T_np, atol=1e-6)):
            raise ConfigError(f"{where}: camera {b.name} ({b.width}x{b.height}) has other intrinsics/extrinsics "
                              f"than the encoder's ({a.width}x{a.height}); the encoder only fits its own cameras")


CAL_THRESHOLDS = tuple(round(0.05 * i, 2) for i in range(1, 20))  # 0.05 … 0.95: the calibration grid


@torch.no_grad()
def episode_counts(encoder, heads, store, slices, fov: np.ndarray, thresholds=CAL_THRESHOLDS, clip_frames: int = 8,
                   clips_per_batch: int = 4, on_batch=None) -> tuple[np.ndarray, np.ndarray]:
    """Intersection and union counts ``E x S x K`` per episode slice, threshold and target (field of view, valid
    frames; on the encoder's device). ``thresholds``: ``S`` (the same for every target) or ``S x K``.
    ``on_batch(batch, logits, labels, valid)``, if given, sees every batch's forward pass too (one pass serves
    several metrics, e.g. :class:`SeenPeopleCounts`)."""
    dev = next(encoder.parameters()).device
    fov_t = torch.from_numpy(fov).to(dev)
    th = torch.as_tensor(thresholds, dtype=torch.float32).to(dev)
    if th.dim() == 1:  # one threshold for every target
        th = th.view(-1, 1).expand(-1, len(TARGETS))
    was = encoder.training, heads.training
    encoder.eval()
    heads.eval()
    inter = np.zeros((len(slices), th.shape[0], len(TARGETS)))
    union = np.zeros_like(inter)
    for e, sl in enumerate(slices):
        for batch in make_batches(make_clips(store, [sl], clip_frames, encoder.frames, None), clips_per_batch,
                                  encoder.frames):
            out = forward_batch(encoder, heads, store, batch)
            i, u = iou_counts(*out, fov_t, th)
            if on_batch is not None:
                on_batch(batch, *out)
            inter[e] += i.cpu().numpy()
            union[e] += u.cpu().numpy()
    encoder.train(was[0])
    heads.train(was[1])
    return inter, union


def _iou(inter: np.ndarray, union: np.ndarray) -> np.ndarray:
    return np.where(union > 0, inter / np.maximum(union, 1), np.nan)


def iou_sweep(encoder, heads, store, slices, fov: np.ndarray, thresholds=THRESHOLDS, clip_frames: int = 8,
              clips_per_batch: int = 4, pos_weight: list[float] | None = None,
              on_batch=None) -> dict[str, dict[str, float]]:
    """``{target: {threshold: IoU}}`` over the frames of ``slices`` (field of view, valid frames only).

    With ``pos_weight`` (the training loss's per-target BCE weights, ``metrics.json``), one more column ``bayes``
    uses the threshold ``w / (1 + w)``: a BCE weighted by ``w`` on positives learns ``w``-inflated odds, so this
    is where the *unweighted* probability crosses 0.5 — the decision rule that does not depend on the weight.
    """
    cols = [f"{x:g}" for x in thresholds]
    th = torch.tensor(thresholds, dtype=torch.float32).view(-1, 1).expand(-1, len(TARGETS))
    if pos_weight is not None:
        w = torch.tensor(pos_weight, dtype=torch.float32)
        th = torch.cat([th, (w / (1 + w)).view(1, -1)], 0)
        cols.append("bayes")
    inter, union = episode_counts(encoder, heads, store, slices, fov, th, clip_frames, clips_per_batch, on_batch)
    iou = _iou(inter.sum(0), union.sum(0))
    return {t: {x: float(iou[i, k]) for i, x in enumerate(cols)} for k, t in enumerate(TARGETS)}


def calibrate(inter: np.ndarray, union: np.ndarray, thresholds=CAL_THRESHOLDS,
              pos_weight: list[float] | None = None, folds: int = 2) -> dict:
    """The decision rule per target, chosen honestly: from per-episode counts (:func:`episode_counts`),

    * ``at_0.5`` — IoU at p > 0.5 (the headline rule before calibration);
    * ``best`` / ``best_threshold`` — the threshold with the best IoU on all these episodes and that IoU
      (optimistic: chosen and scored on the same episodes); ``best_threshold`` is the rule saved for consumers;
    * ``cross_fitted`` — each episode scored at the threshold chosen on the *other* folds' episodes (episodes
      dealt round-robin into ``folds`` folds): the IoU to expect from the saved rule on unseen episodes;
    * ``bayes`` (with the loss's ``pos_weight`` w) — IoU at p > w / (1 + w), where the unweighted probability
      crosses 0.5.
    """
    th = np.asarray(thresholds, float)
    total_i, total_u = inter.sum(0), union.sum(0)  # S x K
    iou_all = _iou(total_i, total_u)
    k_best = np.nanargmax(np.nan_to_num(iou_all, nan=-1.0), 0)  # K
    out = {"thresholds_grid": th.tolist(), "targets": list(TARGETS),
           "at_0.5": _iou(total_i, total_u)[int(np.argmin(np.abs(th - 0.5)))].tolist(),
           "best_threshold": th[k_best].tolist(), "best": iou_all[k_best, np.arange(len(TARGETS))].tolist()}
    fold = np.arange(len(inter)) % folds
    ci, cu = np.zeros(len(TARGETS)), np.zeros(len(TARGETS))
    chosen = []
    for f in range(folds):
        rest = fold != f
        if not rest.any() or not (fold == f).any():
            continue
        kb = np.nanargmax(np.nan_to_num(_iou(inter[rest].sum(0), union[rest].sum(0)), nan=-1.0), 0)
        chosen.append(th[kb].tolist())
        ci += inter[fold == f].sum(0)[kb, np.arange(len(TARGETS))]
        cu += union[fold == f].sum(0)[kb, np.arange(len(TARGETS))]
    out["cross_fitted"] = _iou(ci, cu).tolist()
    out["cross_fit_thresholds"] = chosen
    if pos_weight is not None:
        w = np.asarray(pos_weight, float)
        kb = np.abs(th[:, None] - (w / (1 + w))[None]).argmin(0)  # the grid's nearest threshold
        out["bayes_threshold"] = th[kb].tolist()
        out["bayes"] = iou_all[kb, np.arange(len(TARGETS))].tolist()
    return out


def turning_pedestrian_frame(store, slices, fov: np.ndarray, cell_m: float, min_step_m: float = 0.25,
                             stride: int = 2) -> tuple[int, float] | None:
    """A frame of ``slices`` showing one pedestrian (one connected blob now, at +0.5 s and at +1.0 s, all valid, in
    the field of view) who turns most between the two half-seconds: ``(store index, turn in degrees)``, or None.
    The figure of predicted vs true future occupancy is drawn on it."""

    best: tuple[int, float] | None = None
    for a, b in slices:
        for t in range(a, b, stride):
            if not store.valid[t, 1:4].all():
                continue
            cents = []
            for k in (1, 2, 3):
                lab, n = ndimage.label(store.labels[t, k] & fov)
                if n != 1:
                    break
                cents.append(np.argwhere(lab == 1).mean(0) * cell_m)
            if len(cents) != 3:
                continue
            d1, d2 = cents[1] - cents[0], cents[2] - cents[1]
            n1, n2 = np.linalg.norm(d1), np.linalg.norm(d2)
            if min(n1, n2) < min_step_m:
                continue
            turn = float(np.degrees(np.arccos(np.clip(d1 @ d2 / (n1 * n2), -1.0, 1.0))))
            if best is None or turn > best[1]:
                best = (t, turn)
    return best


class SeenPeopleCounts:
    """The "pedestrians now" IoU with and without the cells of unseen people (module docstring), per threshold,
    accumulated from forward passes made elsewhere: pass it as ``on_batch`` to :func:`episode_counts` /
    :func:`iou_sweep`, then read :meth:`result`."""

    def __init__(self, store, fov: np.ndarray, thresholds=THRESHOLDS):
        if store.seen_now is None:
            raise ConfigError("SeenPeopleCounts needs a store loaded with with_seen_now=True")
        self.store, self.fov = store, fov
        self.cols = [f"{x:g}" for x in thresholds]
        self.th = np.asarray(thresholds, dtype=np.float32)
        self.inter = np.zeros((2, len(self.th)))
        self.union = np.zeros_like(self.inter)
        self.label_cells = self.unseen_cells = 0

    def __call__(self, batch, logits, labels, valid) -> None:
        fov, th = self.fov, self.th
        prob = torch.sigmoid(logits[:, PEOPLE_NOW]).cpu().numpy()
        people = (labels[:, PEOPLE_NOW] > 0.5).cpu().numpy()
        ok = valid[:, PEOPLE_NOW].cpu().numpy()
        seen_now = self.store.seen_now[batch.targets] > 0
        for p in np.flatnonzero(ok):
            true = people[p] & fov
            seen = seen_now[p] & true
            keep = fov & ~(true & ~seen)
            self.label_cells += int(true.sum())
            self.unseen_cells += int((true & ~seen).sum())
            pred = prob[p][None] > th[:, None, None]
            for row, (m, t) in enumerate(((fov, true), (keep, seen))):
                pm = pred & m
                self.inter[row] += (pm & t).sum((1, 2))
                self.union[row] += (pm | t).sum((1, 2))

    def result(self) -> dict:
        iou = _iou(self.inter, self.union)
        return {"all": {c: float(iou[0, i]) for i, c in enumerate(self.cols)},
                "seen_only": {c: float(iou[1, i]) for i, c in enumerate(self.cols)},
                "unseen_share_of_label_cells": self.unseen_cells / max(self.label_cells, 1),
                "label_cells": self.label_cells}


class RegionRates:
    """Per target, over the cells of ``mask`` in valid frames: the mean predicted probability where the label is
    empty and where it is occupied, and the occupied share (module docstring). An ``on_batch`` for
    :func:`episode_counts`; read :meth:`result`."""

    def __init__(self, mask: np.ndarray):
        self.mask = torch.from_numpy(mask)
        self.sums = np.zeros((3, len(TARGETS)))  # probability on empty cells, on occupied cells, occupied cells
        self.cells = np.zeros(len(TARGETS))

    def __call__(self, batch, logits, labels, valid) -> None:
        m = (valid[:, :, None, None] & self.mask.to(logits.device)[None, None]).float()
        prob, occ = torch.sigmoid(logits) * m, (labels > 0.5).float() * m
        self.sums[0] += (prob * (m - occ)).sum((0, 2, 3)).cpu().numpy()
        self.sums[1] += (prob * occ).sum((0, 2, 3)).cpu().numpy()
        self.sums[2] += occ.sum((0, 2, 3)).cpu().numpy()
        self.cells += m.sum((0, 2, 3)).cpu().numpy()

    def result(self) -> dict:
        empty, occ, n = self.cells - self.sums[2], self.sums[2], self.cells
        ratio = lambda a, b: float(a / b) if b > 0 else float("nan")  # noqa: E731
        return {t: {"mean_prob_empty": ratio(self.sums[0, k], empty[k]),
                    "mean_prob_occupied": ratio(self.sums[1, k], occ[k]),
                    "occupied_share": ratio(occ[k], n[k]), "cells": int(n[k])} for k, t in enumerate(TARGETS)}


def evaluate_checkpoint(ckpt: Path, dataset: Path | None = None, episodes: str = "val",
                        thresholds=THRESHOLDS, progress: bool = True, people_label: str | None = None,
                        region: str = "fov") -> dict:
    """Loads a checkpoint and a dataset and returns the IoU sweep with its provenance; the people targets are
    scored against ``people_label`` (``all`` | ``seen``; None: the label the checkpoint was trained on), on the
    cells of ``region`` (:data:`REGIONS`)."""
    if region not in REGIONS:
        raise ConfigError(f"--region: expected one of {list(REGIONS)}, got {region!r}")
    desc = read_encoder_json(ckpt)
    ds = desc.get("dataset", {})
    if dataset is None:
        repo = ds.get("repo_id")
        if not repo:
            raise ConfigError(f"{ckpt}: encoder.json names no dataset; pass --dataset")
        dataset = Path(ckpt).resolve().parents[1] / "datasets" / repo
    dataset = Path(dataset)
    encoder = load_encoder(ckpt)
    heads = load_heads(ckpt, encoder)
    meta = check_dataset(dataset)
    cams = meta.cameras
    check_same_cameras(encoder.cameras, cams, str(dataset))
    fov = check_grid_fits_cameras(encoder.grid, cams)
    if region == "outside":
        fov = ~fov
        if not fov.any():
            raise ConfigError(f"{ckpt}: --region outside: every cell of the grid is in the cameras' view")
    total = int(meta.info["total_episodes"])
    if episodes in ("val", "train"):
        eps = ds.get(f"{episodes}_episodes")
        if eps is None:
            raise ConfigError(f"{ckpt}: encoder.json lists no {episodes} episodes")
    elif episodes == "all":
        eps = list(range(total))
    else:
        try:
            eps = sorted({int(x) for x in episodes.split(",") if x.strip()})
        except ValueError:
            raise ConfigError(f"--episodes: expected val, train, all or a comma list of indices, "
                              f"got {episodes!r}") from None
    bad = [e for e in eps if not 0 <= e < total]
    if bad or not eps:
        raise ConfigError(f"--episodes: {bad or 'none'} not in the dataset's 0..{total - 1}")
    people_label = people_label or desc.get("people_label", "all")
    store = load_frames(dataset, cams, encoder.grid, encoder.cfg.lift_stride_px, desc.get("future_s", [0.5, 1.0]),
                        episodes=eps, progress=progress, people_label=people_label, with_seen_now=True)
    pos_weight = None
    mpath = Path(ckpt) / "metrics.json"
    if mpath.is_file():
        pos_weight = json.loads(mpath.read_text()).get("pos_weight")
    seen = SeenPeopleCounts(store, fov, thresholds)  # both fed by the sweep's forward passes
    rates = RegionRates(fov)

    def on_batch(*args) -> None:
        seen(*args)
        rates(*args)

    sweep = iou_sweep(encoder, heads, store, store.episode_slices, fov, thresholds, pos_weight=pos_weight,
                      on_batch=on_batch)
    return {"checkpoint": str(ckpt), "dataset": str(dataset), "episodes": eps, "frames": len(store),
            "people_label": people_label, "region": region, "iou": sweep, "visible_people": seen.result(),
            "rates": rates.result(),
            "note": f"dataset-level IoU, {'field-of-view' if region == 'fov' else 'out-of-view'} cells, valid frames"}


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pretrain.evaluate", description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--dataset", type=Path, default=None, help="dataset root (default: the one it was trained on)")
    ap.add_argument("--episodes", default="val", help="val | train | all | comma list of episode indices")
    ap.add_argument("--out", type=Path, default=None, help="also write the result as JSON here")
    ap.add_argument("--people-label", choices=PEOPLE_LABELS, default=None,
                    help="score the people targets against all people or only the seen ones (default: the label "
                         "the checkpoint was trained on)")
    ap.add_argument("--region", choices=REGIONS, default="fov",
                    help="score the cells in the cameras' field of view (default) or the rest of the grid")
    a = ap.parse_args(argv)
    res = evaluate_checkpoint(a.checkpoint, a.dataset, a.episodes, people_label=a.people_label, region=a.region)
    print(f"{res['frames']} frames of {len(res['episodes'])} episodes of {res['dataset']} ({res['note']})")
    ths = list(next(iter(res["iou"].values())))
    print(f"{'target':<12}" + "".join(f"  p>{t:<5}" for t in ths) + "   (bayes: p > w/(1+w), w = pos_weight)")
    for t, row in res["iou"].items():
        print(f"{t:<12}" + "".join(f"  {row[x]:<7.3f}" for x in ths))
    vis = res["visible_people"]
    print(f"{'ped_t seen':<12}" + "".join(f"  {vis['seen_only'][x]:<7.3f}" for x in ths if x in vis["seen_only"])
          + f"   (unseen people left out: {100 * vis['unseen_share_of_label_cells']:.1f} % of the label's cells)")
    print(f"{'target':<12}  mean p | empty   mean p | occupied   occupied share   cells")
    for t, r in res["rates"].items():
        print(f"{t:<12}  {r['mean_prob_empty']:<14.3f}  {r['mean_prob_occupied']:<17.3f}  {r['occupied_share']:<15.4f}"
              f"  {r['cells']}")
    if a.out:
        atomic_write_json(a.out, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
