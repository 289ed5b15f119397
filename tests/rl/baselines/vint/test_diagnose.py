"""The ViNT-style diagnosis: its probes, its agreement with the training loss, the CLI and its errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pretrain.data import split_episodes
from rl.baselines.common import load_baseline
from rl.baselines.vint import NAME, Config, Trainer, build_model, load_dataset
from rl.baselines.vint.diagnose import COMPONENTS, diagnose, main, probe_r2


def test_probe_r2_recovers_a_linear_signal_and_not_noise() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 3))
    y = x @ np.array([0.5, -1.0, 2.0]) + 0.3 + 0.01 * rng.normal(size=400)
    assert probe_r2(x[:300], y[:300], x[300:], y[300:]) > 0.999
    noise = rng.normal(size=400)
    assert probe_r2(x[:300], noise[:300], x[300:], noise[300:]) < 0.05


def test_component_errors_average_to_the_training_loss(vint_ckpt: Path) -> None:
    model, desc = load_baseline(vint_ckpt, NAME, build_model)
    frames, _ = load_dataset(Path(desc["produced_by"]["dataset"]), list(model.image_hw), progress=False)
    assert frames.action is not None and frames.action.shape == (len(frames.pose), 2)
    train_eps, val_eps = split_episodes(len(frames.slices), 0.5, 0)
    d = diagnose(model, desc["deploy"], frames, val_eps, train_eps, val_eps)
    assert set(d["components"]) == set(COMPONENTS) and d["frames"] == sum(e - s for s, e in
                                                                            (frames.slices[k] for k in val_eps))
    # the per-component errors are the training's waypoint loss split up (same labels, same network)
    cfg = Config(**{k: v for k, v in desc["net"].items() if k in ("context", "horizon", "image_hw")},
                 spacing=int(desc["deploy"]["spacing"]), goal_scale_m=float(desc["deploy"]["goal_scale_m"]))
    trainer = Trainer(frames, cfg, float(desc["deploy"]["metres_per_step"]))
    loss = trainer.evaluate(model, val_eps)["action_loss"]
    assert np.mean([c["mse"] for c in d["components"].values()]) == pytest.approx(loss, rel=1e-5)
    for c in d["components"].values():
        assert c["r2"] == pytest.approx(1.0 - c["mse"] / c["mean_predictor_mse"])
    assert -1.0 <= d["omega_corr_label"] <= 1.0 and d["goal_mirror_dy_change"] >= 0.0


def test_cli_writes_the_figures_and_names_a_wrong_checkpoint(vint_ckpt: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "diag.json"
    assert main([str(vint_ckpt), "--split", "train", "--val-fraction", "0.5", "--out", str(out)]) == 0
    d = json.loads(out.read_text())
    assert d["split"] == "train" and set(d["probe_r2_dy"]) == {"goal", "motion", "both"}
    assert "mean-predictor MSE" in capsys.readouterr().out
    # a checkpoint of another baseline: one named error, exit 2, nothing written
    other = tmp_path / "other"
    other.mkdir()
    desc = json.loads((vint_ckpt / "policy.json").read_text())
    (other / "policy.json").write_text(json.dumps({**desc, "variant": "drl_vo"}))
    assert main([str(other), "--out", str(tmp_path / "x.json")]) == 2
    assert "expected a 'vint' baseline checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()
