"""The intention model (pretrain.intention): samples replayed through the students' tracker, a pose cue that the pose
model reads and the position model cannot, overfitting a tiny set, the stage on the tiny dataset, checkpoint round
trip, fine-tuning on another distribution, and the named errors."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from pipeline.core.keys import (
    OBS_ODOM,
    OBS_POSE_MASK,
    OBS_POSES,
    PRIV_PED_KEYPOINTS,
    PRIV_PED_STATE,
    PRIV_POSE_TRACK,
)
from pipeline.core.manifest import MANIFEST_NAME
from pipeline.core.stage import run_stage
from pipeline.verbs.pretrain_intention import STAGE
from pretrain import intention
from pretrain.intention import (
    FitOptions,
    ForecasterConfig,
    IntentionConfig,
    IntentionForecaster,
    episode_samples,
    evaluate,
    finetune_forecaster,
    fit_model,
    from_track_frame,
    load_forecaster,
    predict,
    to_track_frame,
)

FPS = 10.0
HORIZONS = [0.2, 0.4, 0.6, 0.8, 1.0]


def walking_episode(t_len: int = 40, v: float = 1.0, robot=(0.0, -3.0, 0.5)) -> dict[str, np.ndarray]:
    """One pedestrian walking along +x at ``v`` m/s from (0, 0), detected every frame with all 17 joints on a
    vertical line through its centre, seen from a robot standing at ``robot``."""
    xy = np.stack([v * np.arange(t_len) / FPS, np.zeros(t_len)], -1)
    state = np.zeros((t_len, 2, 8), np.float32)
    state[:, 0, :2], state[:, 0, 2], state[:, 0, 4], state[:, 0, 7] = xy, v, 0.25, 1.0
    kp_world = np.concatenate([np.repeat(xy[:, None], 17, 1), np.full((t_len, 17, 1), 1.0)], -1)
    rx, ry, ryaw = robot
    c, s = math.cos(ryaw), math.sin(ryaw)
    dx, dy = kp_world[..., 0] - rx, kp_world[..., 1] - ry
    kp_robot = np.stack([c * dx + s * dy, -s * dx + c * dy, kp_world[..., 2]], -1)
    track = np.full((t_len, 2), -1)
    track[:, 0] = 0
    return {OBS_ODOM: np.tile(np.array(robot, np.float32), (t_len, 1)),
            OBS_POSES: np.concatenate([kp_robot[:, None], np.zeros_like(kp_robot)[:, None]], 1).astype(np.float32),
            OBS_POSE_MASK: np.concatenate([np.ones((t_len, 1, 17), bool), np.zeros((t_len, 1, 17), bool)], 1),
            PRIV_PED_STATE: state, PRIV_PED_KEYPOINTS: np.stack([kp_world, np.zeros_like(kp_world)], 1),
            PRIV_POSE_TRACK: track}


def test_track_frames_round_trip():
    rng = np.random.default_rng(0)
    origin, heading = rng.normal(size=(4, 2)), rng.uniform(-3, 3, 4)
    pts = rng.normal(size=(4, 6, 2))
    back = from_track_frame(to_track_frame(pts, origin, heading), origin, heading)
    assert np.allclose(back, pts)


def test_samples_follow_the_tracker_and_label_the_true_future():
    s = episode_samples(walking_episode(), FPS, HORIZONS, 8, episode=3)
    far = round(HORIZONS[-1] * FPS)
    assert len(s["speed"]) == 40 - far and (s["episode"] == 3).all() and not s["turn"].any()
    first, late = 0, len(s["speed"]) - 1
    assert s["hist_valid"][first].sum() == 1 and s["hist_valid"][late].all()  # a young track has one position
    assert s["kp_mask"].all()  # detected every frame: the pose is on the track
    # late in the walk the track has converged: heading along +x, speed ~1 m/s, target = the true future
    assert s["speed"][late] == pytest.approx(1.0, abs=0.1)
    assert abs(s["heading"][late]) < 0.1
    assert s["target"][late][:, 0] == pytest.approx(np.asarray(HORIZONS), abs=0.2)
    # the joints stand on a vertical line through the centre: in the track frame they sit near its origin
    assert np.abs(s["kp"][late, :, :2]).max() < 0.3 and s["kp"][late, :, 2] == pytest.approx(1.0)


def cue_samples(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Walking along +x at 1 m/s; a third turn left, a third right (the turn is in the target only), a third go
    straight. The nose joint (index 0) is 0.3 m to the side of the coming turn — the only cue."""
    rng = np.random.default_rng(seed)
    side = np.tile([-1.0, 0.0, 1.0], n // 3 + 1)[:n]
    h = np.asarray(HORIZONS, np.float32)
    hist = np.stack([np.linspace(-0.7, 0, 8), np.zeros(8)], -1)[None].repeat(n, 0).astype(np.float32)
    hist += rng.normal(0, 0.02, hist.shape).astype(np.float32)
    target = np.stack([h[None].repeat(n, 0), 0.8 * side[:, None] * h[None] ** 2], -1).astype(np.float32)
    kp = rng.normal(0, 0.02, (n, 17, 3)).astype(np.float32)
    kp[:, :, 2] += np.linspace(0.1, 1.7, 17)  # feet to head
    kp[:, 0, 1] += 0.3 * side
    return {"hist": hist, "hist_valid": np.ones((n, 8), bool), "speed": np.ones(n, np.float32), "kp": kp,
            "kp_mask": np.ones((n, 17), bool), "kp_true": kp, "target": target,
            "head": np.stack([np.ones(n), 0.3 * side], -1).astype(np.float32), "turn": side != 0,
            "lead_s": np.where(side != 0, 0.5, np.nan).astype(np.float32), "episode": np.arange(n) % 10,
            "frame": np.arange(n) // 10}


@pytest.mark.slow
def test_the_pose_model_reads_a_turn_cue_the_positions_do_not_have():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small batches: one thread is faster
    try:
        s = cue_samples(600)
        opt = FitOptions(epochs=20, batch=32, lr=3e-3, pose_dropout=0.3, head_aux_weight=0.2, seed=0)
        preds = {"cv": predict(None, s, horizons_s=HORIZONS)}
        for name, pose in (("position", False), ("pose", True)):
            m = IntentionForecaster(ForecasterConfig(history=8, horizons_s=HORIZONS, dim=16, hidden=32, pose=pose))
            preds[name] = predict(fit_model(m, s, s, opt, torch.device("cpu")), s)
    finally:
        torch.set_num_threads(threads)
    r = evaluate(preds, s, HORIZONS, n_boot=20, seed=0)["results"]
    turns = {m: r[m]["turns"]["fde_1s_m"] for m in r}
    straight = s["turn"] == 0
    assert turns["position"] > 0.6 and turns["pose"] < 0.4 * turns["position"], turns  # the side is only in the pose
    for m in ("position", "pose"):  # straight walks: nothing to gain, both close to constant velocity (exact here)
        assert np.linalg.norm(preds[m][straight] - s["target"][straight], axis=-1).mean() < 0.15


def test_a_model_overfits_a_tiny_set():
    s = cue_samples(24, seed=1)
    m = IntentionForecaster(ForecasterConfig(history=8, horizons_s=HORIZONS, dim=8, hidden=32))
    before = float(np.linalg.norm(predict(m, s) - s["target"], axis=-1).mean())
    fit_model(m, s, s, FitOptions(epochs=150, batch=24, lr=1e-2, pose_dropout=0.0, head_aux_weight=0.0, seed=0),
              torch.device("cpu"))
    after = float(np.linalg.norm(predict(m, s) - s["target"], axis=-1).mean())
    assert after < 0.2 * before and after < 0.05, (before, after)


def test_forecaster_config_and_stage_config_refuse_bad_values():
    with pytest.raises(ConfigError, match="horizons_s"):
        ForecasterConfig(horizons_s=[0.4, 0.2]).validate()
    with pytest.raises(ConfigError, match="horizons_s"):
        ForecasterConfig(horizons_s=[0.2, float("nan")]).validate()
    with pytest.raises(ConfigError, match="pose_dropout"):
        IntentionConfig(pose_dropout=1.0).validate()
    with pytest.raises(ConfigError, match="lr"):
        IntentionConfig(lr=float("inf")).validate()


def test_samples_of_the_tiny_recording(tiny_dataset):
    """The real path: parquet columns -> tracker replay -> samples (2 s episodes; one of the two sees people)."""
    s, fps, n = intention.collect(tiny_dataset.root, [0.2, 0.4], 8)
    assert fps == FPS and n == 2 and len(s["speed"]) > 10 and set(s["episode"].tolist()) <= {0, 1}
    for k in ("hist", "target", "kp", "kp_true", "head", "speed"):
        assert np.isfinite(s[k]).all(), k
    assert s["kp_mask"].any(-1).mean() > 0.5  # most tracks carry this frame's pose
    err = np.linalg.norm(s["target"][:, 0], axis=-1)  # the true position 0.2 s later, seen from the track
    assert np.median(err) < 0.6


@pytest.fixture
def intention_ckpt(tmp_path, tiny_dataset, monkeypatch):
    """The stage on a copy of the tiny dataset, its samples replaced by :func:`cue_samples` over 10 episodes (the
    tiny recording's two episodes cannot fill a training and a validation split; its samples are tested above)."""
    dst = tmp_path / "data" / "datasets" / tiny_dataset.repo_id
    shutil.copytree(tiny_dataset.root, dst)
    monkeypatch.setattr(intention, "collect", lambda root, horizons_s, history, max_episodes=0: (
        {k: v[:, -len(horizons_s):] if k == "target" else v for k, v in cue_samples(90).items()}, FPS, 10))
    cfg = IntentionConfig(data_dir=tmp_path / "data", repo_id=tiny_dataset.repo_id, epochs=2, batch=16, bootstrap=5,
                          figures=1, threads=1, val_fraction=0.5, model=ForecasterConfig(horizons_s=[0.2, 0.4],
                                                                                        dim=8, hidden=16))
    run_stage(STAGE, cfg)
    return tmp_path / "data" / "checkpoints" / "intention"


def test_stage_writes_a_checkpoint_that_loads_and_predicts_the_same(intention_ckpt):
    out = intention_ckpt
    for name in ("forecaster.safetensors", "position.safetensors", "intention.json", "metrics.json", "metrics.md",
                 "train_log.csv", "figures/errors.png", "config.yaml", MANIFEST_NAME):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["results"]) == {"cv", "position", "pose", "pose_centroid", "pose_true"}
    assert metrics["results"]["cv"]["all"]["n"] == metrics["samples"]["val"] > 0
    model, desc = load_forecaster(out)
    assert desc["model"]["horizons_s"] == [0.2, 0.4] and model.cfg.pose and not any(
        p.requires_grad for p in model.parameters())
    pos, _ = load_forecaster(out, "position")
    assert not pos.cfg.pose
    s = cue_samples(9)
    s["hist"] = s["hist"][:, -8:]
    again, _ = load_forecaster(out)
    assert np.array_equal(predict(model, s), predict(again, s))


def test_a_damaged_or_unfinished_checkpoint_is_a_named_error(intention_ckpt, tmp_path):
    with pytest.raises(InputMissingError, match="no intention checkpoint"):
        load_forecaster(tmp_path / "nope")
    bad = tmp_path / "bad"
    shutil.copytree(intention_ckpt, bad)
    (bad / "intention.json").write_text("{not json")
    with pytest.raises(CorruptArtifactError, match="intention.json"):
        load_forecaster(bad)
    (bad / MANIFEST_NAME).unlink()
    with pytest.raises(InputMissingError, match="unfinished"):
        load_forecaster(bad)


def test_a_dataset_without_keypoints_is_a_named_error(dataset_copy):
    info = dataset_copy / "meta" / "info.json"
    meta = json.loads(info.read_text())
    del meta["features"][OBS_POSES]
    info.write_text(json.dumps(meta))
    with pytest.raises(InputMissingError, match=OBS_POSES.replace(".", r"\.")):
        intention.collect(dataset_copy, HORIZONS, 8)


def test_fine_tuning_adapts_the_pretrained_model_to_a_new_distribution(intention_ckpt, tmp_path, monkeypatch):
    """The people around the student's robot turn the other way than in the pretraining data (the cue's sign flipped
    in the target): fine-tuning from the pretrained weights must lower the held-out error it reports, and write a
    checkpoint :func:`load_forecaster` reads without a manifest, naming where it came from; the pretrained one is
    untouched and the position model is copied."""
    flipped = cue_samples(120, seed=3)
    flipped["target"] = flipped["target"][:, -2:] * np.array([1.0, -1.0], np.float32)
    seen = []
    monkeypatch.setattr(intention, "collect", lambda root, horizons_s, history, max_episodes=0: (
        seen.append(root) or flipped, FPS, 10))
    before = (intention_ckpt / "forecaster.safetensors").read_bytes()
    out = tmp_path / "policy" / "dagger" / "iter_1" / "intention"
    res = finetune_forecaster(intention_ckpt, [tmp_path / "d0", tmp_path / "d1"], out,
                              FitOptions(epochs=40, batch=16, lr=1e-2, pose_dropout=0.0, head_aux_weight=0.0, seed=0),
                              0.3)
    assert seen == [tmp_path / "d0", tmp_path / "d1"]
    assert res["train_episodes"] + res["val_episodes"] == 20 and res["val_samples"] > 0  # ids made unique per root
    v = res["val"]
    assert v["tuned"]["fde_1s_m"] < 0.5 * v["pretrained"]["fde_1s_m"], v
    model, desc = load_forecaster(out)
    assert desc["tuned_from"] == str(intention_ckpt) and desc["tuning"]["val"] == v
    assert (intention_ckpt / "forecaster.safetensors").read_bytes() == before
    assert (out / "position.safetensors").read_bytes() == (intention_ckpt / "position.safetensors").read_bytes()
    pretrained, _ = load_forecaster(intention_ckpt)
    s = {k: x[:5] for k, x in flipped.items()}
    assert not np.allclose(predict(model, s), predict(pretrained, s))
    (out / "intention.json").unlink()  # weights without their description: not a checkpoint
    with pytest.raises(InputMissingError, match="unfinished"):
        load_forecaster(out)
