"""The pretraining step benchmark (``pretrain.bench.measure_fit_steps``) and the trunk-layout pair
(``measure_trunk_layout``); figures, no timing assertions."""

from __future__ import annotations

import json
import math

import pytest

from pretrain.bench import main, measure_fit_steps, measure_trunk_layout
from pretrain.geometry import cameras_from_dataset
from pretrain.model import BEVEncoder, EncoderConfig
from tests.pretrain.test_train import ENC


@pytest.mark.parametrize("fuse_pool", [1, 2])
def test_fit_step_figures_on_the_cpu(tiny_dataset, fuse_pool) -> None:
    out = measure_fit_steps(cameras_from_dataset(tiny_dataset.root), EncoderConfig(**ENC, fuse_pool=fuse_pool),
                            ["cpu"], steps=1, clips_per_batch=1, clip_frames=2)
    assert set(out) == {"pretrain_step_ms_cpu"} and math.isfinite(out["pretrain_step_ms_cpu"]) and out[
        "pretrain_step_ms_cpu"] > 0


def test_cli_asks_for_cuda_without_it_is_a_named_error(tiny_dataset, capsys, monkeypatch) -> None:
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main(["--dataset", str(tiny_dataset.root), "--devices", "cuda", "--steps", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: device:") and "CUDA is not available" in err[0]
    assert main(["--dataset", str(tiny_dataset.root), "--devices", "cpu", "--steps", "1", "--clips-per-batch", "1",
                 "--clip-frames", "2"]) == 0
    assert json.loads(capsys.readouterr().out)["pretrain_step_ms_cpu"] > 0
    # --profile: the profile's encoder and batch, unless the batch is given
    assert main(["--dataset", str(tiny_dataset.root), "--devices", "cpu", "--steps", "1", "--profile", "default",
                 "--clips-per-batch", "1", "--clip-frames", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["profile"] == "default" and (out["clips_per_batch"], out["clip_frames"]) == (1, 2)
    assert out["pretrain_step_ms_cpu"] > 0 and out["bev_grid_cells"] > 0
    assert main(["--dataset", str(tiny_dataset.root), "--devices", "cpu", "--profile", "nosuch"]) == 2
    assert "unknown profile 'nosuch'" in capsys.readouterr().err
    # a pooled fusion that does not fit the grid is named before anything is timed
    assert main(["--dataset", str(tiny_dataset.root), "--devices", "cpu", "--fuse-pool", "7"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: encoder.fuse_pool: expected a divisor of both BEV grid sizes [60, 96], got 7"]


def test_intention_fit_figures_from_a_samples_file(tmp_path) -> None:
    """The samples file round trip (what travels to a GPU machine) and the fit's figures per device."""
    import numpy as np

    from pretrain.bench import measure_intention_fit
    from pretrain.intention import ForecasterConfig
    from tests.pretrain.test_intention import cue_samples

    s = cue_samples(60)
    h = np.asarray(ForecasterConfig().horizons_s, np.float32)  # the bench fits the default model's horizons
    s["target"] = np.stack([np.broadcast_to(h, (60, len(h))), np.zeros((60, len(h)), np.float32)], -1)
    np.savez_compressed(tmp_path / "s.npz", fps=np.float64(10.0), n_episodes=np.int64(10), **s)
    out = measure_intention_fit(tmp_path / "s.npz", ["cpu"], epochs=1)
    assert out["intention_epochs"] == 1 and 0 < out["intention_train_samples"] < 60
    assert out["intention_fit_s_cpu"] > 0 and math.isfinite(out["intention_val_fde_last_m_cpu"])
    assert "intention_fit_speedup_cuda_vs_cpu" not in out  # one device: no ratio


def test_trunk_layout_figures_leave_the_encoder_as_they_found_it(tiny_dataset) -> None:
    import torch

    enc = BEVEncoder(EncoderConfig(**ENC), cameras_from_dataset(tiny_dataset.root)).eval()
    before = {k: v.clone() for k, v in enc.state_dict().items()}
    out = measure_trunk_layout(enc, images=2, rounds=1)
    assert set(out) == {"trunk_train_ms_nchw", "trunk_train_ms_channels_last", "trunk_train_speedup_channels_last"}
    assert all(math.isfinite(v) and v > 0 for v in out.values())
    assert out["trunk_train_speedup_channels_last"] == out["trunk_train_ms_nchw"] / out["trunk_train_ms_channels_last"]
    # measured on a copy: the encoder's weights, BatchNorm statistics, gradients and mode are untouched
    assert not enc.training and all(p.grad is None for p in enc.parameters())
    assert all(torch.equal(v, before[k]) for k, v in enc.state_dict().items())
