"""Deploying the ViNT-style baseline: the context buffer, ViNT's controller, the checkpoint driving the same episode in
a fresh process, a corrupt checkpoint."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.errors import CorruptArtifactError
from rl.baselines.vint import ContextBuffer, Driver, vint_controller
from tests.rl.baselines.vint.helpers import rollout


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


@pytest.mark.slow
def test_checkpoint_drives_the_same_episode_in_a_fresh_process(vint_ckpt: Path) -> None:
    here = np.array(rollout(str(vint_ckpt)))
    script = ("import json, sys; from tests.rl.baselines.vint.helpers import rollout; "
              "print(json.dumps(rollout(sys.argv[1])))")
    run = subprocess.run([sys.executable, "-c", script, str(vint_ckpt)], cwd=Path(__file__).resolve().parents[4],
                         capture_output=True, text=True, timeout=300)
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
