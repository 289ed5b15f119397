"""Our datasets through stock LeRobot tooling: ``lerobot-train`` (ACT), ``delete_episodes`` / ``remove_feature``, and
LeRobot's action convention (``action[t]`` is the command chosen from observation ``t``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from recorder.dataset_info import read_dataset_info
from recorder.doctor_dataset import check_dataset
from recorder.drive import drive_episode
from recorder.export import export_dataset
from tests.conftest import TinyDataset, tiny_sim_config


def _lerobot_env(tmp_path: Path) -> dict[str, str]:
    """Offline, with lerobot's and HF's caches inside ``tmp_path`` (nothing written to ``~/.cache``)."""
    return {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf"), "WANDB_MODE": "disabled",
            "HF_LEROBOT_HOME": str(tmp_path / "lerobot_home")}


def test_stock_lerobot_train_runs_act_on_the_dataset(tiny_dataset: TinyDataset, tmp_path: Path) -> None:
    """lerobot's own CLI, ACT on every observation feature it takes (state, poses, masks, depth, images), a few
    steps on CPU, no pretrained backbone (nothing from a hub)."""
    out = tmp_path / "act"
    cmd = [str(Path(sys.executable).with_name("lerobot-train")),
           f"--dataset.repo_id={tiny_dataset.repo_id}", f"--dataset.root={tiny_dataset.root}",
           "--policy.type=act", "--policy.device=cpu", "--policy.push_to_hub=false",
           "--policy.pretrained_backbone_weights=null", "--policy.dim_model=32", "--policy.n_heads=2",
           "--policy.dim_feedforward=64", "--policy.n_encoder_layers=1", "--policy.n_decoder_layers=1",
           "--policy.chunk_size=10", "--policy.n_action_steps=10", "--policy.use_vae=false",
           "--steps=3", "--batch_size=2", "--num_workers=0", "--log_freq=1", "--save_checkpoint=false",
           "--wandb.enable=false", f"--output_dir={out}"]
    res = subprocess.run(cmd, capture_output=True, text=True, env=_lerobot_env(tmp_path), timeout=600)
    log = res.stdout + res.stderr
    assert res.returncode == 0, log[-3000:]
    assert "End of training" in log, log[-3000:]
    losses = [float(w.split(":")[1]) for line in log.splitlines() if "step:" in line
              for w in line.split() if w.startswith("loss:")]
    assert len(losses) == 3 and all(np.isfinite(losses)), log[-3000:]
    assert f"dataset.num_frames={tiny_dataset.counts['frames']}" in log


def test_delete_episodes_and_remove_feature_keep_the_calibration(tiny_dataset: TinyDataset, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    from lerobot.datasets.dataset_tools import delete_episodes, remove_feature
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    for k, v in _lerobot_env(tmp_path).items():
        monkeypatch.setenv(k, v)
    src = LeRobotDataset(tiny_dataset.repo_id, root=tiny_dataset.root, video_backend="pyav")
    want = read_dataset_info(tiny_dataset.root)
    kept = delete_episodes(src, [0], output_dir=tmp_path / "one", repo_id="icrowdnav/one")
    lean = remove_feature(src, [k for k in src.meta.features if k.startswith(("observation.depth.", "privileged."))],
                          output_dir=tmp_path / "lean", repo_id="icrowdnav/lean")
    lengths = [int(n) for n in src.meta.episodes["length"]]
    assert kept.meta.total_episodes == 1 and len(kept) == lengths[1]
    assert lean.meta.total_episodes == 2 and len(lean) == sum(lengths)
    for root in (tmp_path / "one", tmp_path / "lean"):
        got = read_dataset_info(root)  # the format and every camera's calibration survived lerobot's tools
        assert got.cameras == want.cameras and got.fps == want.fps
        assert not (root / "meta" / "icrowdnav.json").exists()  # the side files are extras lerobot drops
        assert check_dataset(root) == [], root
    assert read_dataset_info(tmp_path / "one").local_map == want.local_map
    # the kept episode's rows are the source's second episode, frame for frame
    a, b = src[lengths[0]], kept[0]
    for key in ("observation.state", "action", "observation.depth.left", "privileged.ped_state"):
        np.testing.assert_array_equal(a[key].numpy(), b[key].numpy(), err_msg=key)
    assert not any(k.startswith(("observation.depth.", "privileged.")) for k in lean.meta.features)
    stock = json.loads((tmp_path / "lean" / "meta" / "info.json").read_text())["features"]
    assert stock["observation.images.left"]["info"]["camera"] == want.cameras["left"]


class ScriptedDriver:
    """Chooses each command from the observation it is given, by a fixed function of ``obs["state"]``."""

    def reset(self, obs, info) -> None:
        pass

    @staticmethod
    def command(state: np.ndarray) -> np.ndarray:
        """A continuous action in [-1, 1]² that changes from step to step with the goal's position."""
        return np.array([np.sin(7.0 * state[2]), np.cos(5.0 * state[1])], np.float32)

    def act(self, obs, info) -> np.ndarray:
        return self.command(obs["state"])


def test_action_t_is_the_command_chosen_from_observation_t(tmp_path: Path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from sim.env import CrowdNavEnv

    cfg = tiny_sim_config()
    recorded = drive_episode(cfg, 3, ScriptedDriver())
    frames = list(recorded.frames)
    recorded.frames = iter(frames)
    export_dataset([recorded], tmp_path / "ds", "icrowdnav/scripted", progress=False)
    ds = LeRobotDataset("icrowdnav/scripted", root=tmp_path / "ds", video_backend="pyav")
    assert len(ds) == len(frames) - 1 >= 5
    codec_env = CrowdNavEnv(config=cfg)  # decodes an action into the physical command, as the env did
    commands = []
    for t in range(len(ds)):
        item = ds[t]
        state = item["observation.state"].numpy()
        np.testing.assert_array_equal(state, frames[t].state)  # observation t
        want = np.asarray(codec_env.decode_action(ScriptedDriver.command(state)), np.float32)
        np.testing.assert_allclose(item["action"].numpy(), want, rtol=0, atol=1e-6, err_msg=f"frame {t}")
        assert float(item["next.reward"]) == np.float32(frames[t + 1].reward)
        assert bool(item["next.done"]) == (t == len(ds) - 1)
        commands.append(want)
    assert len({tuple(c) for c in commands}) > len(commands) // 2  # the script really varies the command
