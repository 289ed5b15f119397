"""Intention probe: does a person's pose say where they will walk, beyond what their past positions say?

Read from a recorded LeRobot dataset only (its parquet files; no video): for every detected and tracked pedestrian
(``privileged.pose_track``) at every frame, predict its displacement at +0.5 s and +1.0 s from

* ``cv``           constant velocity (its current velocity × the horizon);
* ``position``     a small MLP on its past positions (the last 0.8 s) — the position-only model;
* ``pose_detected``  the same plus the keypoints the robot *detected* (``observation.poses``: noisy, partly
                   occluded, lifted with depth), through the I²Former's pose encoder (φ_p + joint embedding +
                   IntentFormer, :class:`pretrain.i2former.I2Former`);
* ``pose_true``    the same with the simulator's true keypoints (``privileged.ped_keypoints``): the ceiling of what
                   the pose holds;
* ``head_true``    the position model plus the true head yaw relative to the walking direction: the one cue our
                   humans announce a turn with (``sim.intention``), given directly.

Everything is expressed in the pedestrian's frame at the prediction time (origin at its position, x along its
walking direction), so a model cannot learn the scene, only the person. Training and validation are split by
episode. Reported per model, on the validation episodes: ADE (mean error over the two horizons) and FDE (error at
+1.0 s), over all samples and over *turn events* — the walking direction changes by ≥ 45° within the next 1.0 s —
split by how long before the turn (the walking direction crossing half of it) the prediction is made.

Positions and velocities are the simulator's (``privileged.ped_state``) for every model, so the comparison isolates
what the pose adds; the keypoints of ``pose_detected`` are what the robot saw. ::

    python -m pretrain.probe --dataset data/datasets/icrowdnav/expert --out data/probe
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from pipeline.core.artifacts import atomic_write_json, atomic_write_text, json_safe
from pipeline.core.errors import ConfigError, InputMissingError, reports_errors
from pipeline.core.keys import (
    OBS_ODOM,
    OBS_POSE_MASK,
    OBS_POSES,
    PRIV_PED_KEYPOINTS,
    PRIV_PED_STATE,
    PRIV_POSE_TRACK,
)
from pretrain.data import check_dataset, split_episodes
from pretrain.figures import plot_model_errors
from pretrain.i2former import N_JOINTS, I2Former, I2FormerConfig
from pretrain.schedule import one_cycle
from recorder.dataset_info import read_dataset_info

log = logging.getLogger("icrowdnav")

HORIZONS_S = (0.5, 1.0)
HISTORY_S = 0.8  # past positions the models see
TURN_DEG = 45.0  # a turn event: the walking direction changes by at least this within the last horizon
MIN_SPEED = 0.3  # m/s: below it the walking direction is not defined (no turn event is counted)
LEAD_BINS_S = ((0.0, 0.3), (0.3, 0.6), (0.6, 1.01))
MODELS = ("cv", "position", "pose_detected", "pose_true", "head_true")


@dataclass
class ProbeConfig:
    """Options of the probe (``python -m pretrain.probe --help``)."""

    dataset: Path = Path("data/datasets/icrowdnav/expert")
    out: Path = Path("data/probe")
    epochs: int = 12
    batch: int = 256
    lr: float = 3e-3
    val_fraction: float = 0.2
    seed: int = 0
    dim: int = 32  # I²Former width of the pose models
    max_samples: int = 200_000  # training samples drawn at most (seeded), to bound the run time

    def validate(self) -> None:
        for name, lo in (("epochs", 1), ("batch", 1), ("dim", 4), ("max_samples", 100)):
            if getattr(self, name) < lo:
                raise ConfigError(f"probe.{name}: expected >= {lo}, got {getattr(self, name)}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise ConfigError(f"probe.lr: expected a positive finite number, got {self.lr}")
        if not 0 < self.val_fraction < 1:
            raise ConfigError(f"probe.val_fraction: expected a number in (0, 1), got {self.val_fraction}")


# ------------------------------------------------------------------------------------------------ the samples
@dataclass
class Samples:
    """One row per (frame, detected and tracked pedestrian) with the full horizon inside its episode.

    ``hist`` H x 2 past positions, ``target`` 2 x 2 displacements at :data:`HORIZONS_S`, ``kp_det`` / ``kp_true``
    17 x 3 keypoints (``kp_mask`` the detected joints) — all in the pedestrian's frame; ``speed`` m/s, ``head`` the
    head yaw relative to the walking direction (rad), ``turn`` / ``lead_s`` the turn event and how long before it,
    ``view`` 0 when the pedestrian faces the robot, π when it turns its back to it.
    """

    hist: np.ndarray
    target: np.ndarray
    kp_det: np.ndarray
    kp_mask: np.ndarray
    kp_true: np.ndarray
    speed: np.ndarray
    head: np.ndarray
    turn: np.ndarray
    lead_s: np.ndarray
    episode: np.ndarray
    view: np.ndarray  # angle between where the head faces and the robot, seen from the pedestrian (rad, 0..π)

    def take(self, idx: np.ndarray) -> Samples:
        return Samples(**{k: v[idx] for k, v in self.__dict__.items()})

    def __len__(self) -> int:
        return len(self.speed)


def _column(table, name: str, shape: tuple[int, ...], dtype=np.float32) -> np.ndarray:
    """A (nested) list column as a ``rows x shape`` array, without going through Python lists."""
    import pyarrow as pa

    col = table.column(name).combine_chunks()
    while pa.types.is_list(col.type) or pa.types.is_large_list(col.type) or pa.types.is_fixed_size_list(col.type):
        col = col.flatten()
    values = np.asarray(col.to_numpy(zero_copy_only=False), dtype=dtype)
    return values.reshape(table.num_rows, *shape)


def read_episodes(root: Path) -> list[dict[str, np.ndarray]]:
    """The columns the probe reads, one dict per episode (frames in order)."""
    import pyarrow.parquet as pq

    root = Path(root)
    meta = check_dataset(root)
    feats = meta.info["features"]
    for key in (OBS_POSES, OBS_POSE_MASK, PRIV_PED_KEYPOINTS, PRIV_POSE_TRACK, OBS_ODOM):
        if key not in feats:
            raise InputMissingError(f"dataset {root} lacks {key}, which the intention probe reads")
    k, n = feats[OBS_POSES]["shape"][0] // (N_JOINTS * 3), feats[PRIV_PED_STATE]["shape"][0]  # poses are flat
    files = sorted((root / "data").rglob("*.parquet"))
    cols = ["episode_index", "frame_index", OBS_ODOM, OBS_POSES, OBS_POSE_MASK, PRIV_PED_STATE, PRIV_PED_KEYPOINTS,
            PRIV_POSE_TRACK]
    parts: dict[str, list[np.ndarray]] = {c: [] for c in cols}
    for f in files:
        t = pq.read_table(f, columns=cols)
        parts["episode_index"].append(t.column("episode_index").to_numpy())
        parts["frame_index"].append(t.column("frame_index").to_numpy())
        parts[OBS_ODOM].append(_column(t, OBS_ODOM, (3,)))
        parts[OBS_POSES].append(_column(t, OBS_POSES, (k, N_JOINTS, 3)))
        parts[OBS_POSE_MASK].append(_column(t, OBS_POSE_MASK, (k, N_JOINTS), bool))
        parts[PRIV_PED_STATE].append(_column(t, PRIV_PED_STATE, (n, 8)))
        parts[PRIV_PED_KEYPOINTS].append(_column(t, PRIV_PED_KEYPOINTS, (n, N_JOINTS, 3)))
        parts[PRIV_POSE_TRACK].append(_column(t, PRIV_POSE_TRACK, (k,), np.int64))
    data = {c: np.concatenate(v) for c, v in parts.items()}
    order = np.lexsort((data["frame_index"], data["episode_index"]))
    data = {c: v[order] for c, v in data.items()}
    cuts = np.flatnonzero(np.diff(data["episode_index"])) + 1
    return [{c: v[a:b] for c, v in data.items()}
            for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(order)], strict=True)]


def _to_frame(xy: np.ndarray, origin: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """World ``... x S x 2`` points into per-sample frames (``S`` origins, headings); broadcast over leading dims."""
    c, s = np.cos(heading), np.sin(heading)
    d = xy - origin
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def episode_samples(ep: dict[str, np.ndarray], fps: float, episode: int) -> Samples | None:
    """The samples of one episode (see :class:`Samples`)."""
    hist_n = round(HISTORY_S * fps)
    hz = [round(h * fps) for h in HORIZONS_S]
    far = hz[-1]
    state = ep[PRIV_PED_STATE]  # T x N x 8: x, y, vx, vy, radius, body yaw, head yaw, present
    t_len = len(state)
    track = ep[PRIV_POSE_TRACK]  # T x K
    tt, kk = np.nonzero(track >= 0)
    keep = (tt >= hist_n) & (tt + far < t_len)
    tt, kk = tt[keep], kk[keep]
    nn_ = track[tt, kk]
    window = tt[:, None] + np.arange(-hist_n, far + 1)[None]  # S x W
    present = state[window, nn_[:, None], 7] > 0.5
    ok = present.all(1)
    tt, kk, nn_, window = tt[ok], kk[ok], nn_[ok], window[ok]
    if len(tt) == 0:
        return None
    pos = state[window, nn_[:, None], :2]  # S x W x 2
    vel = state[window, nn_[:, None], 2:4]
    now = hist_n
    p0, v0 = pos[:, now], vel[:, now]
    speed = np.hypot(v0[:, 0], v0[:, 1])
    heading = np.where(speed > 0.1, np.arctan2(v0[:, 1], v0[:, 0]), state[tt, nn_, 5])
    local = _to_frame(pos.transpose(1, 0, 2), p0, heading).transpose(1, 0, 2)  # S x W x 2
    hist = local[:, :now]
    target = local[:, [now + h for h in hz]]
    # keypoints: true ones are world frame; detected ones robot frame -> world with the robot's odometry
    kp_true = ep[PRIV_PED_KEYPOINTS][tt, nn_]  # S x 17 x 3
    kp_det = ep[OBS_POSES][tt, kk]
    mask = ep[OBS_POSE_MASK][tt, kk]
    odom = ep[OBS_ODOM][tt]
    c, s = np.cos(odom[:, 2])[:, None], np.sin(odom[:, 2])[:, None]
    det_world = np.stack([odom[:, :1] + c * kp_det[..., 0] - s * kp_det[..., 1],
                          odom[:, 1:2] + s * kp_det[..., 0] + c * kp_det[..., 1]], -1)

    def local_kp(world_xy: np.ndarray, z: np.ndarray) -> np.ndarray:
        xy = _to_frame(world_xy.transpose(1, 0, 2), p0, heading).transpose(1, 0, 2)
        return np.concatenate([xy, z[..., None]], -1).astype(np.float32)

    kp_det_l = np.where(mask[..., None], local_kp(det_world, kp_det[..., 2]), 0.0)
    kp_true_l = local_kp(kp_true[..., :2], kp_true[..., 2])
    head = _wrap(state[tt, nn_, 6] - heading)
    to_robot = np.arctan2(odom[:, 1] - p0[:, 1], odom[:, 0] - p0[:, 0])
    view = np.abs(_wrap(state[tt, nn_, 6] - to_robot))
    # turn events: the walking direction at +1.0 s differs by >= TURN_DEG; lead = until it crosses half the turn
    ang = np.arctan2(vel[:, now:, 1], vel[:, now:, 0])
    spd = np.hypot(vel[:, now:, 0], vel[:, now:, 1])
    rel = _wrap(ang - ang[:, :1])
    total = rel[:, -1]
    turn = (np.abs(total) >= math.radians(TURN_DEG)) & (spd[:, 0] >= MIN_SPEED) & (spd[:, -1] >= MIN_SPEED)
    crossed = np.abs(rel) >= np.abs(total)[:, None] / 2
    first = np.argmax(crossed, axis=1)
    lead = np.where(turn, first / fps, np.nan)
    return Samples(hist.astype(np.float32), target.astype(np.float32), kp_det_l, mask, kp_true_l,
                   speed.astype(np.float32), head.astype(np.float32), turn, lead.astype(np.float32),
                   np.full(len(tt), episode), view.astype(np.float32))


def collect(root: Path) -> tuple[Samples, float]:
    """Every sample of a dataset, and its frame rate."""
    fps = float(read_dataset_info(root).fps)
    parts = [s for e, ep in enumerate(read_episodes(root)) if (s := episode_samples(ep, fps, e)) is not None]
    if not parts:
        raise InputMissingError(f"dataset {root}: no tracked pedestrian is seen for {HISTORY_S + HORIZONS_S[-1]:g} s "
                                "in a row; the probe has nothing to predict")
    return Samples(**{k: np.concatenate([getattr(p, k) for p in parts]) for k in parts[0].__dict__}), fps


# ------------------------------------------------------------------------------------------------ the models
class Probe(nn.Module):
    """Constant velocity + a learned correction from the past positions and, optionally, a pose or the head yaw."""

    def __init__(self, hist_n: int, cue: str, dim: int):
        super().__init__()
        self.cue = cue
        extra = {"position": 0, "head_true": 2}.get(cue, dim)
        if cue in ("pose_detected", "pose_true"):
            self.pose = I2Former(I2FormerConfig(dim=dim, heads=4, ffn_mult=2))
        self.head = nn.Sequential(nn.Linear(hist_n * 2 + 1 + extra, 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(),
                                  nn.Linear(64, 2 * len(HORIZONS_S)))

    def forward(self, b: dict[str, torch.Tensor]) -> torch.Tensor:
        x = [b["hist"].flatten(1), b["speed"][:, None]]
        if self.cue == "head_true":
            x.append(torch.stack([torch.cos(b["head"]), torch.sin(b["head"])], -1))
        elif self.cue == "pose_detected":
            x.append(self.pose.person_features(b["kp_det"][:, None], b["kp_mask"][:, None])[0][:, 0])
        elif self.cue == "pose_true":
            x.append(self.pose.person_features(b["kp_true"][:, None], torch.ones_like(b["kp_mask"])[:, None])[0][:, 0])
        return cv_prediction(b["speed"]) + self.head(torch.cat(x, -1)).view(-1, len(HORIZONS_S), 2)


def cv_prediction(speed: torch.Tensor) -> torch.Tensor:
    """Constant velocity in the pedestrian's frame: ``speed × horizon`` along x."""
    h = torch.tensor(HORIZONS_S, dtype=speed.dtype)
    return torch.stack([speed[:, None] * h, torch.zeros_like(speed[:, None] * h)], -1)


def _tensors(s: Samples) -> dict[str, torch.Tensor]:
    return {"hist": torch.from_numpy(s.hist), "speed": torch.from_numpy(s.speed), "head": torch.from_numpy(s.head),
            "kp_det": torch.from_numpy(s.kp_det), "kp_mask": torch.from_numpy(s.kp_mask),
            "kp_true": torch.from_numpy(s.kp_true), "target": torch.from_numpy(s.target)}


def train_probe(cue: str, train: Samples, cfg: ProbeConfig, hist_n: int) -> Probe:
    torch.manual_seed(cfg.seed)
    model = Probe(hist_n, cue, cfg.dim)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    data = _tensors(train)
    gen = torch.Generator().manual_seed(cfg.seed)
    steps = math.ceil(len(train) / cfg.batch)
    sched = one_cycle(opt, cfg.lr, cfg.epochs * steps)
    model.train()
    for _ in range(cfg.epochs):
        order = torch.randperm(len(train), generator=gen)
        for i in range(steps):
            idx = order[i * cfg.batch:(i + 1) * cfg.batch]
            b = {k: v[idx] for k, v in data.items()}
            loss = (model(b) - b["target"]).norm(dim=-1).mean()  # the metric itself: mean displacement error
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
    return model.eval()


@torch.no_grad()
def predict(model: Probe | None, s: Samples, batch: int = 4096) -> np.ndarray:
    data = _tensors(s)
    if model is None:
        return cv_prediction(data["speed"]).numpy()
    return np.concatenate([model({k: v[i:i + batch] for k, v in data.items()}).numpy()
                           for i in range(0, len(s), batch)])


def errors(pred: np.ndarray, s: Samples) -> dict[str, dict[str, float]]:
    """ADE / FDE (m) and counts over all samples, turn events, and turn events by lead time."""
    err = np.linalg.norm(pred - s.target, axis=-1)  # S x horizons
    groups = {"all": np.ones(len(s), bool), "turns": s.turn}
    for lo, hi in LEAD_BINS_S:
        groups[f"turns_lead_{lo:g}-{min(hi, 1.0):g}s"] = s.turn & (s.lead_s > lo) & (s.lead_s <= hi)
    return {g: {"n": int(m.sum()), "ade_m": float(err[m].mean()) if m.any() else float("nan"),
                "fde_m": float(err[m, -1].mean()) if m.any() else float("nan")} for g, m in groups.items()}


HEAD_JOINTS = (0, 1, 2, 3, 4)  # COCO-17: nose, eyes, ears
NOSE, LEFT_EAR, RIGHT_EAR = 0, 3, 4


def _head_yaw(kp: np.ndarray) -> np.ndarray:
    """Facing direction of a head from its keypoints: the nose seen from the midpoint of the ears (rad)."""
    v = kp[:, NOSE, :2] - (kp[:, LEFT_EAR, :2] + kp[:, RIGHT_EAR, :2]) / 2
    return np.arctan2(v[:, 1], v[:, 0])


def detection_stats(s: Samples) -> dict[str, float]:
    """How much of the pose cue survives detection: the share of joints (and head joints) detected, the error of a
    detected joint against the true one (m), and the error of the head's facing direction read from detected nose
    and ears against the same from the true keypoints (degrees) — the cue a turn is announced with."""
    m = s.kp_mask
    err = np.linalg.norm(s.kp_det - s.kp_true, axis=-1)
    head = np.array(HEAD_JOINTS)
    ok = m[:, NOSE] & m[:, LEFT_EAR] & m[:, RIGHT_EAR]
    yaw_err = np.degrees(np.abs(_wrap(_head_yaw(s.kp_det) - _head_yaw(s.kp_true))))

    def q(a: np.ndarray, p: float) -> float:
        return float(np.percentile(a, p)) if a.size else float("nan")

    out = {"joints_detected": float(m.mean()), "head_joints_detected": float(m[:, head].mean()),
           "joint_error_m_median": q(err[m], 50), "joint_error_m_p90": q(err[m], 90),
           "head_joint_error_m_median": q(err[:, head][m[:, head]], 50),
           "nose_and_ears_detected": float(ok.mean()),
           "head_yaw_error_deg_median": q(yaw_err[ok], 50), "head_yaw_error_deg_p90": q(yaw_err[ok], 90)}
    view = np.degrees(s.view)  # by where the head faces: the robot (< 60°), sideways, away from it (> 120°)
    for name, sel in (("facing", view < 60), ("sideways", (view >= 60) & (view <= 120)), ("away", view > 120)):
        out[f"nose_and_ears_detected_{name}"] = float(ok[sel].mean()) if sel.any() else float("nan")
        out[f"head_yaw_error_deg_median_{name}"] = q(yaw_err[ok & sel], 50)
    return out


def run_probe(cfg: ProbeConfig) -> dict:
    """Collects the samples, trains the learned probes on the training episodes, evaluates every model on the
    validation episodes, and writes ``probe.json``, ``probe.md`` and ``probe.png`` into ``cfg.out``."""
    cfg.validate()
    t0 = time.monotonic()
    samples, fps = collect(cfg.dataset)
    n_ep = int(samples.episode.max()) + 1
    train_eps, val_eps = split_episodes(n_ep, cfg.val_fraction, cfg.seed)
    train = samples.take(np.flatnonzero(np.isin(samples.episode, train_eps)))
    val = samples.take(np.flatnonzero(np.isin(samples.episode, val_eps)))
    for part, name in ((train, "training"), (val, "validation")):
        if len(part) == 0:
            raise InputMissingError(f"dataset {cfg.dataset}: its {name} episodes hold no pedestrian tracked for "
                                    f"{HISTORY_S + HORIZONS_S[-1]:g} s; record longer or more episodes")
    if len(train) > cfg.max_samples:
        train = train.take(np.sort(np.random.default_rng(cfg.seed).choice(len(train), cfg.max_samples, False)))
    hist_n = train.hist.shape[1]
    log.info("probe: %d training / %d validation samples (%d / %d turn events), %d episodes", len(train), len(val),
             int(train.turn.sum()), int(val.turn.sum()), n_ep)
    results: dict[str, dict] = {}
    seconds: dict[str, float] = {}
    for name in MODELS:
        t = time.monotonic()
        model = None if name == "cv" else train_probe(name, train, cfg, hist_n)
        results[name] = errors(predict(model, val), val)
        seconds[name] = round(time.monotonic() - t, 1)
        log.info("probe: %-13s FDE all %.3f m, turns %.3f m", name, results[name]["all"]["fde_m"],
                 results[name]["turns"]["fde_m"])
    report = {"dataset": str(cfg.dataset), "config": {k: str(v) if isinstance(v, Path) else v
                                                      for k, v in asdict(cfg).items()},
              "fps": fps, "horizons_s": list(HORIZONS_S), "history_s": HISTORY_S, "turn_deg": TURN_DEG,
              "episodes": {"train": len(train_eps), "val": len(val_eps)},
              "samples": {"train": len(train), "val": len(val), "val_turns": int(val.turn.sum())},
              "detection": detection_stats(val), "results": results, "model_seconds": seconds,
              "seconds": round(time.monotonic() - t0, 1)}
    cfg.out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(cfg.out / "probe.json", json_safe(report))  # NaN (an empty group) -> null
    atomic_write_text(cfg.out / "probe.md", markdown(report))
    figure(report, cfg.out / "probe.png")
    return report


def markdown(report: dict) -> str:
    res = report["results"]
    groups = list(res["cv"])
    head = "| model | " + " | ".join(f"{g} FDE (ADE), m [n={res['cv'][g]['n']}]" for g in groups) + " |"
    lines = [head, "|" + "---|" * (len(groups) + 1)]
    for name, r in res.items():
        lines.append(f"| {name} | " + " | ".join(f"{r[g]['fde_m']:.3f} ({r[g]['ade_m']:.3f})" for g in groups) + " |")
    if "detection" in report:
        lines += ["", "detection (validation samples): " + ", ".join(f"{k} {v:.3g}" for k, v in
                                                                  report["detection"].items())]
    return "\n".join(lines) + "\n"


def figure(report: dict, path: Path) -> None:
    plot_model_errors(path, report["results"], "fde_m", "FDE at +1.0 s (m)",
                      "Where a pedestrian is 1 s later: positions alone vs + pose (validation episodes)")


@reports_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pretrain.probe", description=__doc__.split("\n\n")[0])
    defaults = ProbeConfig()
    for f in ProbeConfig.__dataclass_fields__.values():
        ap.add_argument(f"--{f.name.replace('_', '-')}", type=type(getattr(defaults, f.name)),
                        default=getattr(defaults, f.name))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname).1s %(message)s", datefmt="%H:%M:%S")
    report = run_probe(ProbeConfig(**{k.replace("-", "_"): v for k, v in vars(args).items()}))
    print(markdown(report), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

