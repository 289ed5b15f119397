"""The ViNT-style checkpoint the driver tests share (trained once per package on the tests' tiny dataset)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rl.baselines.vint import inputs, train
from tests.conftest import TinyDataset
from tests.rl.baselines.vint.helpers import Log, train_cfg


@pytest.fixture(scope="package")
def vint_ckpt(tmp_path_factory: pytest.TempPathFactory, tiny_dataset: TinyDataset) -> Path:
    """A ViNT-style checkpoint trained for one epoch on the tests' tiny recorded dataset."""
    data = tmp_path_factory.mktemp("vint_data")
    (data / "datasets" / "icrowdnav").mkdir(parents=True)
    (data / "datasets" / "icrowdnav" / "tiny").symlink_to(tiny_dataset.root)
    cfg = train_cfg(data)
    assert any(p.suffix == ".mp4" for p in inputs(cfg))
    out = data / "checkpoints" / "policy" / "vint"
    log = Log()
    summary = train(cfg, out, log)
    assert summary["budget"]["episodes"] == 2 and summary["budget"]["frames"] == 40  # 2 episodes x (21 recorded - the terminal one)
    assert any(phase == "epoch" for phase, _, _ in log.rows)
    return out
