"""The ViNT-style baseline: labels, context buffer and controller on constructed data; it learns a visual cue; its
checkpoint drives the same episode in a fresh process; corrupt / missing inputs; the released-layout loader."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from rl.baselines.vint import (
    Config,
    ContextBuffer,
    Driver,
    Frames,
    Trainer,
    build_model,
    context_indices,
    efficientnet_pytorch_b0_keys,
    inputs,
    load_released_weights,
    train,
    trajectory_labels,
    vint_controller,
)
from rl.stage import TrainConfig
from tests.conftest import TinyDataset, tiny_sim_config

TINY_NET = {"embed_dim": 32, "layers": 1, "heads": 2, "output_layers": [32, 16], "image_hw": [12, 16]}


class _Log:
    def __init__(self) -> None:
        self.rows: list[tuple[str, int, dict]] = []

    def add(self, phase: str, step: int, **values: float) -> None:
        self.rows.append((phase, step, values))


# ------------------------------------------------------------------------------------------------ labels, buffer
def test_trajectory_labels_on_a_known_track() -> None:
    # heading +y at 1 m/s for 5 frames, then turning left on the spot by 0.1 rad per frame; 10 frames at 10 fps
    yaw = np.pi / 2 + np.r_[np.zeros(5), 0.1 * np.arange(1, 6)]
    y = np.r_[0.1 * np.arange(5), np.full(5, 0.4)]
    pose = np.stack([np.zeros(10), y, yaw], -1)
    goal = np.tile([0.0, 5.0], (10, 1))
    wp, dist, g = trajectory_labels(pose, goal, np.array([0, 4, 8]), np.full(3, 10), horizon=3, spacing=2,
                                    metres_per_step=0.2, max_dist=3)
    # frame 0: poses of frames 2, 4, 6 straight ahead (0.2, 0.4 m), then 0.4 m ahead turned by 0.2 rad
    np.testing.assert_allclose(wp[0, :, :2], [[1.0, 0.0], [2.0, 0.0], [2.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(wp[0, :, 2:], [[1, 0], [1, 0], [math.cos(0.2), math.sin(0.2)]], atol=1e-6)
    # frame 4: on the spot, yaw +0.2, +0.4, +0.5 (frame 9 past the end: held at the last pose)
    np.testing.assert_allclose(wp[1, :, :2], 0.0, atol=1e-6)
    np.testing.assert_allclose(np.arctan2(wp[1, :, 3], wp[1, :, 2]), [0.2, 0.4, 0.5], atol=1e-6)
    np.testing.assert_allclose(np.arctan2(wp[2, :, 3], wp[2, :, 2]), [0.1, 0.1, 0.1], atol=1e-6)
    np.testing.assert_allclose(dist, [3.0, 2.5, 0.5])  # (9 - t) / 2, capped at 3
    # goal 5 m ahead at frame 0; at frame 8 (yaw +0.4) it lies to the right
    np.testing.assert_allclose(g[0], [5.0, 0.0], atol=1e-6)
    assert g[2, 1] < 0


def test_context_indices_repeat_the_first_frame() -> None:
    ctx = context_indices(np.array([10, 13, 20]), np.array([10, 10, 10]), context=2, spacing=2)
    np.testing.assert_array_equal(ctx, [[10, 10, 10], [10, 11, 13], [16, 18, 20]])


def test_context_buffer_on_constructed_frames() -> None:
    buf = ContextBuffer(context=2, spacing=2)
    frames = [np.full((1, 2), k) for k in range(8)]
    buf.push(frames[0])
    np.testing.assert_array_equal(buf.window()[:, 0, 0], [0, 0, 0])
    for f in frames[1:4]:
        buf.push(f)
    np.testing.assert_array_equal(buf.window()[:, 0, 0], [0, 1, 3])
    for f in frames[4:]:
        buf.push(f)
    np.testing.assert_array_equal(buf.window()[:, 0, 0], [3, 5, 7])
    buf.reset()
    buf.push(frames[5])
    np.testing.assert_array_equal(buf.window()[:, 0, 0], [5, 5, 5])


def test_vint_controller() -> None:
    assert vint_controller(np.array([0.3, 0.0, 1, 0]), 0.2, 1.0, 2.0) == (1.0, 0.0)  # v = 1.5 clipped
    v, w = vint_controller(np.array([0.1, 0.01, 1, 0]), 0.2, 1.0, 2.0)
    assert v == pytest.approx(0.5) and w == pytest.approx(math.atan(0.1) / 0.2)
    assert vint_controller(np.array([0.0, -0.1, 1, 0]), 0.2, 1.0, 2.0) == (0.0, -2.0)
    assert vint_controller(np.array([0.0, 0.0, 0.0, 1.0]), 0.2, 1.0, 2.0) == (0.0, 2.0)
    assert vint_controller(np.array([-0.5, 0.0, 1, 0]), 0.2, 1.0, 2.0)[0] == 0.0  # never backwards


def test_config_validate() -> None:
    Config().validate()
    for bad, word in ((dict(encoder="resnet"), "encoder"), (dict(waypoint_index=5), "waypoint_index"),
                      (dict(embed_dim=30, heads=4), "embed_dim"), (dict(image_hw=[4, 40]), "image_hw"),
                      (dict(val_fraction=1.0), "val_fraction")):
        with pytest.raises(ConfigError, match=word):
            Config(**bad).validate()


# ------------------------------------------------------------------------------------------------------- learning
def _turn_world(n_eps: int, rng: np.random.Generator) -> tuple[Frames, np.ndarray]:
    """Episodes that turn left or right at 1 rad/s; the only cue is a dark block in the camera on the side the
    robot turns away from; the goal is always 3 m straight ahead (no cue)."""
    length, h, w = 20, 12, 16
    turn = rng.choice([-1.0, 1.0], n_eps)
    images = rng.integers(90, 160, (n_eps * length, 3, h, 2 * w)).astype(np.uint8)
    poses, slices = [], []
    for e, d in enumerate(turn):
        yaw = rng.uniform(-np.pi, np.pi) + d * 0.1 * np.arange(length)
        xy = np.cumsum(0.1 * np.stack([np.cos(yaw), np.sin(yaw)], -1), 0)
        poses.append(np.c_[xy, yaw])
        block = slice(0, w) if d < 0 else slice(w, 2 * w)  # obstacle on the left -> turn right (d = -1)
        images[e * length:(e + 1) * length, :, 3:9, block] = 20
        slices.append((e * length, (e + 1) * length))
    pose = np.concatenate(poses)
    goal = pose[:, :2] + 3.0 * np.stack([np.cos(pose[:, 2]), np.sin(pose[:, 2])], -1)
    return Frames(images, pose, goal, slices), turn


def test_learns_a_visual_turn_cue() -> None:
    torch.set_num_threads(1)
    frames, turn = _turn_world(24, np.random.default_rng(0))
    cfg = Config(context=1, horizon=3, spacing=1, epochs=12, clip_len=10, clips_per_batch=4, lr=2e-3,
                 mirror=False, **TINY_NET)
    torch.manual_seed(0)
    model = build_model(cfg.net())
    trainer = Trainer(frames, cfg, metres_per_step=0.1)
    train_eps, held = list(range(20)), list(range(20, 24))
    before = trainer.evaluate(model, held)["action_loss"]
    hist = trainer.fit(model, train_eps, held, seed=0)
    assert hist["train_loss"][-1] < 0.3 * hist["train_loss"][0], hist["train_loss"]
    assert hist["val"][-1]["action_loss"] < 0.3 * before, (before, hist["val"][-1])
    targets = np.concatenate([np.arange(*frames.slices[e]) for e in held])
    b = trainer.batch(targets, mirror=False)
    with torch.no_grad():
        _, wp = model.head(model.encode(b.frames)[b.window], b.goal)
    side = np.sign(wp[:, -1, 1].numpy())  # lateral offset of the last waypoint
    want = np.repeat(turn[held], 20)
    assert (side == want).mean() > 0.9, (side, want)


# ------------------------------------------------------------------------------------------ checkpoint, deployment
def _train_cfg(data_dir: Path, **vint) -> TrainConfig:
    v = Config(repo_id="icrowdnav/tiny", epochs=1, clip_len=8, clips_per_batch=2, val_fraction=0.5, **TINY_NET)
    return TrainConfig(data_dir=data_dir, variant="vint", seed=0, threads=1, progress=False, vint=replace(v, **vint))


@pytest.fixture(scope="module")
def vint_ckpt(tmp_path_factory: pytest.TempPathFactory, tiny_dataset: TinyDataset) -> Path:
    """A ViNT-style checkpoint trained for one epoch on the tests' tiny recorded dataset."""
    data = tmp_path_factory.mktemp("vint_data")
    (data / "datasets" / "icrowdnav").mkdir(parents=True)
    (data / "datasets" / "icrowdnav" / "tiny").symlink_to(tiny_dataset.root)
    cfg = _train_cfg(data)
    assert any(p.suffix == ".mp4" for p in inputs(cfg))
    out = data / "checkpoints" / "policy" / "vint"
    log = _Log()
    summary = train(cfg, out, log)
    assert summary["budget"]["episodes"] == 2 and summary["budget"]["frames"] == 42
    assert any(phase == "epoch" for phase, _, _ in log.rows)
    return out


def _rollout(ckpt: str) -> list[list[float]]:
    """The driver's actions over the first steps of a seeded visual episode (tiny cameras)."""
    from sim.env import CrowdNavEnv

    torch.set_num_threads(1)
    driver = Driver(Path(ckpt))
    env = CrowdNavEnv(config=replace(tiny_sim_config(), density=0.1, obs_mode="visual"))
    obs, _ = env.reset(seed=3)
    driver.reset(env, obs)
    actions = []
    for _ in range(8):
        a = driver.act(env, obs)
        actions.append(np.asarray(a, float).tolist())
        obs, _, term, trunc, _ = env.step(a)
        if term or trunc:
            break
    env.close()
    return actions


def test_checkpoint_drives_the_same_episode_in_a_fresh_process(vint_ckpt: Path) -> None:
    here = np.array(_rollout(str(vint_ckpt)))
    script = ("import json, sys; from tests.rl.baselines.test_vint import _rollout; "
              "print(json.dumps(_rollout(sys.argv[1])))")
    run = subprocess.run([sys.executable, "-c", script, str(vint_ckpt)], cwd=Path(__file__).resolve().parents[3],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    fresh = np.array(json.loads(run.stdout.strip().splitlines()[-1]))
    assert here.shape == fresh.shape and len(here) >= 5 and np.all(np.abs(here) <= 1.0)
    np.testing.assert_allclose(fresh, here, atol=1e-6)


def test_corrupt_checkpoint_names_the_file(vint_ckpt: Path, tmp_path: Path) -> None:
    import shutil

    bad = tmp_path / "vint"
    shutil.copytree(vint_ckpt, bad)
    (bad / "policy.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(CorruptArtifactError, match="policy.safetensors"):
        Driver(bad)


def test_missing_dataset(tmp_path: Path) -> None:
    with pytest.raises(InputMissingError, match=r"make record") as e:
        inputs(_train_cfg(tmp_path))
    assert str(tmp_path / "datasets" / "icrowdnav" / "tiny") in str(e.value)


# ------------------------------------------------------------------------------------------------ released layout
FAITHFUL = {"encoder": "efficientnet_b0", "image_hw": [64, 85], "context": 5, "horizon": 5, "embed_dim": 512,
            "layers": 4, "heads": 4, "ff_factor": 4, "output_layers": [256, 128, 64, 32]}


def _released_layout(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """A state dict as the released ViNT names it: efficientnet_pytorch encoder keys, its classifier and an
    image-goal encoder we do not use."""
    sd = model.state_dict()
    enc = [k for k in sd if k.startswith("obs_encoder.")]
    out = {f"obs_encoder.{n}": sd[k] for k, n in zip(enc, efficientnet_pytorch_b0_keys(), strict=True)}
    out |= {k: v for k, v in sd.items() if not k.startswith(("obs_encoder.", "goal_mlp."))}
    out["obs_encoder._fc.weight"] = torch.zeros(1000, 1280)
    out["goal_encoder._conv_stem.weight"] = torch.zeros(32, 6, 3, 3)
    return out


def test_released_layout_loads_and_misfits_are_named(tmp_path: Path) -> None:
    torch.manual_seed(0)
    src = build_model(FAITHFUL)
    path = tmp_path / "vint_state.pth"
    torch.save({"model": _released_layout(src)}, path)
    torch.manual_seed(1)
    dst = build_model(FAITHFUL)
    report = load_released_weights(dst, path)
    assert "goal_encoder._conv_stem.weight" in report["ignored"] and "obs_encoder._fc.weight" in report["ignored"]
    assert report["kept"] and all(k.startswith("goal_mlp.") for k in report["kept"])
    for (k, a), b in zip(src.state_dict().items(), dst.state_dict().values(), strict=True):
        assert torch.equal(a, b) != k.startswith("goal_mlp."), k
    broken = _released_layout(src)
    broken["decoder.output_layers.0.weight"] = torch.zeros(512, 100)
    del broken["dist_predictor.0.bias"]
    torch.save(broken, path)
    with pytest.raises(CorruptArtifactError, match=r"vint_state\.pth.*dist_predictor\.0\.bias") as e:
        load_released_weights(dst, path)
    assert "decoder.output_layers.0.weight" in str(e.value)
    path.write_bytes(b"garbage")
    with pytest.raises(CorruptArtifactError, match="vint_state.pth"):
        load_released_weights(dst, path)
    with pytest.raises(ConfigError, match="faithful-size"):
        load_released_weights(build_model(Config(**TINY_NET).net()), path)
