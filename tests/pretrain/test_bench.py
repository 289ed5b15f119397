"""The pretraining step benchmark (``pretrain.bench.measure_fit_steps``; figures, no timing assertions)."""

from __future__ import annotations

import json
import math

from pretrain.bench import main, measure_fit_steps
from pretrain.geometry import cameras_from_dataset
from pretrain.model import EncoderConfig
from tests.pretrain.test_train import ENC


def test_fit_step_figures_on_the_cpu(tiny_dataset) -> None:
    out = measure_fit_steps(cameras_from_dataset(tiny_dataset.root), EncoderConfig(**ENC), ["cpu"], steps=1,
                            clips_per_batch=1, clip_frames=2)
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
