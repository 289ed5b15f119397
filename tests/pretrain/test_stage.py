"""``icrowdnav pretrain`` end to end on the tiny dataset, the checkpoint loader, and bad inputs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from pipeline.core.config import load_config
from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError
from pipeline.core.stage import run_stage_ex
from pipeline.verbs.pretrain import STAGE
from pretrain.checkpoint import ENCODER_WEIGHTS, load_encoder, load_heads
from pretrain.model import BEVStream
from pretrain.quantize import load_frozen_encoder
from pretrain.stage import PretrainConfig, checkpoint_dir, int8_verdict

REPO = "icrowdnav/tiny"
ROOT = Path(__file__).resolve().parents[2]


def _data_dir(tmp_path: Path, dataset: Path) -> Path:
    data = tmp_path / "data"
    shutil.copytree(dataset, data / "datasets" / REPO)
    return data


def _cfg(data: Path, **over) -> PretrainConfig:
    base = {"repo_id": REPO, "epochs": 1, "clip_frames": 8, "clips_per_batch": 2, "figures": 1,
            "progress": False, "encoder.bev_channels": 8, "checkpoint_every_steps": 2}
    base.update(over)
    raw = {k: ",".join(map(str, v)) if isinstance(v, list) else str(v).lower() if isinstance(v, bool) else str(v)
           for k, v in base.items()}
    return load_config(PretrainConfig, "pretrain", "smoke", overrides={"data_dir": str(data), **raw})


@pytest.fixture(scope="module")
def trained(tmp_path_factory, tiny_dataset) -> tuple[PretrainConfig, Path]:
    """One real stage run on the tiny dataset (shared by the tests that read its outputs)."""
    tmp = tmp_path_factory.mktemp("pretrain")
    data = _data_dir(tmp, tiny_dataset.root)
    cfg = _cfg(data)
    manifest, ran = run_stage_ex(STAGE, cfg, ["test"])
    assert ran
    return cfg, checkpoint_dir(cfg)


def test_stage_writes_the_documented_tree(trained) -> None:
    cfg, out = trained
    for name in ("encoder.safetensors", "heads.safetensors", "encoder.json", "metrics.json", "train_log.csv",
                 "manifest.json", "config.yaml", "state/last.pt", "figures/curves.png", "figures/fov.png",
                 "figures/sample_0.png", "int8_calibration.safetensors"):
        assert (out / name).is_file(), name
    assert any((out / "tb").iterdir())
    metrics = json.loads((out / "metrics.json").read_text())
    for t in ("static", "ped_t", "ped_t+0.5s", "ped_t+1.0s"):
        assert f"iou_{t}" in metrics["final"]
    int8 = metrics["int8"]  # the int8 version's calibration and its validation metrics (pretrain.quantize)
    assert int8["calibration_target_frames"] > 0 and int8["calibration_clips"] > 0
    assert isinstance(metrics["int8_usable"], bool)  # whether encoder_precision int8 will take it
    assert set(metrics["final"]) <= set(int8) | {"epoch", "step"}
    dec = metrics["decision"]  # the calibrated decision rule (pretrain.evaluate.calibrate)
    assert metrics["thresholds"] == dec["best_threshold"] and len(dec["best_threshold"]) == 4
    assert set(dec) >= {"at_0.5", "best", "cross_fitted", "bayes", "bayes_threshold", "cross_fit_thresholds"}
    desc = json.loads((out / "encoder.json").read_text())
    assert desc["encoder"]["bev_channels"] == 8 and len(desc["cameras"]) == 2
    assert desc["encoder"]["evidence"] is True and desc["encoder"]["decoder"] == "unet"
    assert desc["dataset"]["repo_id"] == REPO
    assert set(desc["dataset"]["train_episodes"]).isdisjoint(desc["dataset"]["val_episodes"])


def test_second_run_is_up_to_date(trained) -> None:
    cfg, _ = trained
    _, ran = run_stage_ex(STAGE, cfg, ["test"])
    assert not ran


def test_loaded_encoder_is_frozen_and_streams(trained, tiny_dataset) -> None:
    """The loader needs only the checkpoint directory; the loaded encoder reproduces the saved weights."""
    _, out = trained
    enc = load_encoder(out)
    assert not enc.training and not any(p.requires_grad for p in enc.parameters())
    heads = load_heads(out, enc)
    c, x, y = enc.out_shape
    stream = BEVStream(enc)
    cam = enc.cameras[0]
    rgb = torch.randint(0, 255, (1, 2, 3, cam.height, cam.width), dtype=torch.uint8)
    depth = torch.full((1, 2, cam.height, cam.width), 3.0)
    s = stream.step(rgb, depth, torch.zeros(1, 3, dtype=torch.float64))
    assert s.shape == (1, c, x, y) and torch.isfinite(s).all()
    assert heads(s).shape == (1, 4, x, y)
    q = load_frozen_encoder(out, "int8")  # the int8 version from the calibration the stage saved
    assert BEVStream(q).step(rgb, depth, torch.zeros(1, 3, dtype=torch.float64)).shape == (1, c, x, y)


def test_corrupt_or_unfinished_checkpoint_is_named(trained, tmp_path: Path) -> None:
    _, out = trained
    bad = tmp_path / "bev"
    shutil.copytree(out, bad)
    w = bad / ENCODER_WEIGHTS
    w.write_bytes(w.read_bytes()[:100])
    with pytest.raises(CorruptArtifactError, match=str(w)):
        load_encoder(bad)
    (bad / "manifest.json").unlink()
    with pytest.raises(InputMissingError, match="unfinished"):
        load_encoder(bad)
    with pytest.raises(InputMissingError, match="no BEV encoder checkpoint"):
        load_encoder(tmp_path / "nowhere")


def test_mismatching_weights_are_named(trained, tmp_path: Path) -> None:
    """encoder.json and the weights disagree (e.g. edited channels): the error names the weights file."""
    _, out = trained
    bad = tmp_path / "bev"
    shutil.copytree(out, bad)
    desc = json.loads((bad / "encoder.json").read_text())
    desc["encoder"]["bev_channels"] = 16
    (bad / "encoder.json").write_text(json.dumps(desc))
    with pytest.raises(CorruptArtifactError, match="does not match"):
        load_encoder(bad)


def test_dataset_without_needed_features(tmp_path: Path, tiny_dataset) -> None:
    data = _data_dir(tmp_path, tiny_dataset.root)
    info = data / "datasets" / REPO / "meta" / "info.json"
    d = json.loads(info.read_text())
    del d["features"]["privileged.ped_state"]
    info.write_text(json.dumps(d))
    with pytest.raises(InputMissingError, match="privileged.ped_state"):
        run_stage_ex(STAGE, _cfg(data), ["test"])
    assert not (data / "checkpoints").exists() or not any((data / "checkpoints").iterdir())


def test_missing_dataset(tmp_path: Path) -> None:
    with pytest.raises(InputMissingError, match="no LeRobot dataset"):
        run_stage_ex(STAGE, _cfg(tmp_path / "data"), ["test"])


def test_grid_that_does_not_fit_the_cameras(tmp_path: Path, tiny_dataset) -> None:
    data = _data_dir(tmp_path, tiny_dataset.root)
    with pytest.raises(ConfigError, match="max_depth_m"):
        run_stage_ex(STAGE, _cfg(data, **{"encoder.x_bound": [0.0, 12.0, 0.1]}), ["test"])
    with pytest.raises(ConfigError, match="field of view"):
        run_stage_ex(STAGE, _cfg(data, **{"encoder.x_bound": [-6.0, -1.0, 0.1]}), ["test"])
    assert not (data / "checkpoints" / "bev").exists()


def test_cli_bad_grid_is_one_line_and_writes_nothing(tmp_path: Path, tiny_dataset, capsys) -> None:
    from pipeline import cli

    data = _data_dir(tmp_path, tiny_dataset.root)
    rc = cli.main(["pretrain", "--profile", "smoke", "--data-dir", str(data), "--repo-id", REPO,
                   "--encoder.x_bound", "0,12,0.1"])
    err = capsys.readouterr().err
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert rc == 2 and len(errors) == 1 and "max_depth_m" in errors[0], err
    assert not (data / "checkpoints").exists() or not any((data / "checkpoints").iterdir())


def test_cli_device_cuda_without_cuda_is_one_line_and_writes_nothing(tmp_path: Path, tiny_dataset, capsys,
                                                                     monkeypatch) -> None:
    """``--device cuda`` on a machine without CUDA: exit 2, one ``error:`` line naming pretrain.device, no output."""
    from pipeline import cli

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    data = _data_dir(tmp_path, tiny_dataset.root)
    rc = cli.main(["pretrain", "--profile", "smoke", "--data-dir", str(data), "--repo-id", REPO, "--device", "cuda"])
    err = capsys.readouterr().err
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert rc == 2 and len(errors) == 1, err
    assert "pretrain.device" in errors[0] and "CUDA is not available" in errors[0] and "'cuda'" in errors[0], err
    assert not (data / "checkpoints").exists() or not any((data / "checkpoints").iterdir())
    with pytest.raises(ConfigError, match="pretrain.device: expected one of auto, cpu, cuda, cuda:N, got 'gpu'"):
        load_config(PretrainConfig, "pretrain", "smoke", overrides={"device": "gpu"})


def test_manifest_records_the_device(trained) -> None:
    """The counts say which hardware trained it (here the default, auto); the device is not in the config hash."""
    from pipeline.core.device import resolve_device

    cfg, out = trained
    manifest = json.loads((out / "manifest.json").read_text())
    used = str(resolve_device("auto", "pretrain.device"))
    assert manifest["counts"]["device"] == used and manifest["params"]["device"] == "auto"
    assert json.loads((out / "metrics.json").read_text())["device"] == used
    _, ran = run_stage_ex(STAGE, _cfg(out.parents[1], device=used), ["test"])
    assert not ran  # the same run named with its concrete device is up to date


def test_config_errors() -> None:
    with pytest.raises(ConfigError, match="future_s"):
        load_config(PretrainConfig, "pretrain", "smoke", overrides={"future_s": "0.5"})
    with pytest.raises(ConfigError, match="val_fraction"):
        load_config(PretrainConfig, "pretrain", "smoke", overrides={"val_fraction": "1.5"})
    with pytest.raises(ConfigError, match="resnet_stages"):
        load_config(PretrainConfig, "pretrain", "smoke", overrides={"encoder.resnet_stages": "7"})
    with pytest.raises(ConfigError, match="encoder.decoder"):
        load_config(PretrainConfig, "pretrain", "smoke", overrides={"encoder.decoder": "fpn"})
    with pytest.raises(ConfigError, match="pos_weight_cap"):
        load_config(PretrainConfig, "pretrain", "smoke", overrides={"pos_weight_cap": "0.5"})
    with pytest.raises(ConfigError, match=r"pretrain.people_label: expected one of \['all', 'seen'\], got 'visible'"):
        load_config(PretrainConfig, "pretrain", "smoke", overrides={"people_label": "visible"})
    with pytest.raises(ConfigError, match=r"pretrain.precision: expected one of auto, fp32, bf16, got 'fp16'"):
        load_config(PretrainConfig, "pretrain", "smoke", overrides={"precision": "fp16"})


def test_an_encoder_json_from_before_the_evidence_and_decoder_loads_as_trained(trained, tmp_path: Path) -> None:
    """A checkpoint written before ``evidence`` / ``decoder`` existed is the architecture without them."""
    from pretrain.checkpoint import encoder_from_json, read_encoder_json

    _, out = trained
    desc = read_encoder_json(out)
    old = {**desc, "encoder": {k: v for k, v in desc["encoder"].items() if k not in ("evidence", "decoder")}}
    enc = encoder_from_json(old)
    assert not enc.cfg.evidence and enc.cfg.decoder == "none"
    assert not hasattr(enc, "evidence") and not hasattr(enc, "decoder")
    # one written before ``fuse_pool`` (with evidence and decoder) fuses at full resolution
    newer = {**desc, "encoder": {k: v for k, v in desc["encoder"].items() if k != "fuse_pool"}}
    enc = encoder_from_json(newer)
    assert enc.cfg.fuse_pool == 1 and enc.cfg.decoder == "unet" and not hasattr(enc, "refine")


def test_backbone_initialised_from_a_user_weights_file(tmp_path: Path) -> None:
    """A torchvision resnet18 state dict initialises the kept trunk stages; a wrong file is named."""
    import torchvision

    from pretrain.geometry import Camera
    from pretrain.model import BEVEncoder, EncoderConfig
    from pretrain.stage import load_backbone_weights
    from sim.cameras import CameraSpec

    torch.manual_seed(1)
    ref = torchvision.models.resnet18(weights=None)
    path = tmp_path / "resnet18.pth"
    torch.save(ref.state_dict(), path)
    cams = [Camera.from_dict(CameraSpec(n, 64, 48, 70.0, y, 0.0, (0.1, 0.03 * s, 0.8)).to_dict())
            for n, y, s in (("left", 35.0, 1), ("right", -35.0, -1))]
    enc = BEVEncoder(EncoderConfig(resnet_stages=2), cams)
    assert not torch.equal(enc.trunk[4][0].conv1.weight, ref.layer1[0].conv1.weight)
    load_backbone_weights(enc, str(path))
    assert torch.equal(enc.trunk[0].weight, ref.conv1.weight)
    assert torch.equal(enc.trunk[5][1].conv2.weight, ref.layer2[1].conv2.weight)
    bad = tmp_path / "bad.pth"
    torch.save({"fc.weight": torch.zeros(3)}, bad)
    with pytest.raises(CorruptArtifactError, match="bad.pth"):
        load_backbone_weights(enc, str(bad))
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(CorruptArtifactError, match="junk.pth"):
        load_backbone_weights(enc, str(junk))


def test_evaluate_checkpoint_sweeps_thresholds(trained, tiny_dataset, tmp_path: Path) -> None:
    """`python -m pretrain.evaluate` on the trained checkpoint: one IoU per target and threshold (+ bayes)."""
    from pretrain.evaluate import main

    _, out = trained
    dest = tmp_path / "eval.json"
    assert main([str(out), "--episodes", "all", "--out", str(dest)]) == 0
    res = json.loads(dest.read_text())
    assert res["frames"] == tiny_dataset.counts["frames"] and res["episodes"] == [0, 1]
    for row in res["iou"].values():
        assert set(row) == {"0.3", "0.4", "0.5", "0.6", "0.7", "0.8", "0.9", "bayes"}
        assert all(v != v or 0.0 <= v <= 1.0 for v in row.values())  # NaN when a target never occurs
    # the visible-people IoU counts the same cells as the sweep when nobody is left out, and never fewer seen ones
    vis = res["visible_people"]
    for t, v in vis["all"].items():
        assert v == pytest.approx(res["iou"]["ped_t"][t], nan_ok=True)
    assert 0.0 <= vis["unseen_share_of_label_cells"] <= 1.0 and vis["label_cells"] > 0
    rates = res["rates"]["ped_t"]
    assert res["region"] == "fov" and 0.0 < rates["occupied_share"] < 1.0 and rates["cells"] > 0
    assert 0.0 <= rates["mean_prob_empty"] <= 1.0 and 0.0 <= rates["mean_prob_occupied"] <= 1.0
    # the cells outside the cameras' view instead: with those in view, every cell of the grid in each valid frame
    # (a target's valid frames differ: the futures end earlier), so (in + out) / in is the same for every target
    outside = tmp_path / "outside.json"
    assert main([str(out), "--episodes", "all", "--region", "outside", "--out", str(outside)]) == 0
    res_out = json.loads(outside.read_text())
    assert res_out["region"] == "outside" and set(res_out["iou"]) == set(res["iou"])
    ratios = [(r["cells"] + res_out["rates"][t]["cells"]) / r["cells"] for t, r in res["rates"].items()]
    assert ratios[0] > 1.0 and ratios == pytest.approx([ratios[0]] * len(ratios))
    assert main([str(out), "--episodes", "7"]) == 2


def test_the_pretraining_verdict_on_its_int8_version():
    final = {"iou_static": 0.926, "iou_ped_t": 0.49}
    assert int8_verdict(final, None) is None
    assert int8_verdict(final, {"iou_static": 0.92, "iou_ped_t": 0.48}) is True
    assert int8_verdict(final, {"iou_static": 0.70, "iou_ped_t": 0.48}) is False
    assert int8_verdict(final, {"iou_static": float("nan"), "iou_ped_t": 0.48}) is False
