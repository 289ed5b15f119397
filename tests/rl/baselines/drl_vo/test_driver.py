"""DRL-VO's driver: reloading in a fresh process reproduces the actions; a corrupt checkpoint names the file."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from pipeline.core.errors import CorruptArtifactError
from rl.baselines import drl_vo
from tests.rl.baselines.drl_vo.helpers import ROOT, drive

# every test here needs the package's `trained` fixture (a training run, 20-35 s on 2 cores)
pytestmark = pytest.mark.slow

_DRIVE_SCRIPT = """
import json, sys
import torch
from pathlib import Path
from tests.rl.baselines.drl_vo.helpers import drive
torch.set_num_threads(1)
print(json.dumps(drive(Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]))))
"""


def test_reloads_in_a_fresh_process_and_reproduces_its_actions(trained):
    torch.set_num_threads(1)
    outcome, actions = drive(trained["ckpt"], trained["scene"], 123)
    res = subprocess.run([sys.executable, "-c", _DRIVE_SCRIPT, str(trained["ckpt"]), trained["scene"], "123"],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    outcome2, actions2 = json.loads(res.stdout.strip().splitlines()[-1])
    assert outcome2 == outcome
    np.testing.assert_allclose(np.array(actions2), np.array(actions), atol=1e-5)


def test_corrupt_checkpoint_names_the_file(trained, tmp_path):
    bad = tmp_path / "drl_vo"
    shutil.copytree(trained["ckpt"], bad, ignore=shutil.ignore_patterns("ppo", "bc"))
    (bad / "policy.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(CorruptArtifactError, match="policy.safetensors"):
        drl_vo.Driver(bad)


@pytest.mark.timeout(180)
def test_acceptance_in_a_pool_after_torch_ran_multithreaded_gives_the_serial_rows(trained):
    """``rl.evaluate`` forks episode workers from a process whose torch has run on several threads (as after
    training): each worker runs torch on one thread (a forked OpenMP pool can hang), and the rows equal a serial run."""
    from dataclasses import replace

    from rl.evaluate import evaluate
    from sim.env import SimConfig

    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    torch.randn(256, 256) @ torch.randn(256, 256)  # the parent's thread pool is up
    try:
        sim = replace(SimConfig(), max_episode_s=4.0)
        cells = [(trained["scene"], 0.0)]
        pooled = evaluate(trained["ckpt"], sim, cells, [1, 2], workers=2, progress=False)
        serial = evaluate(trained["ckpt"], sim, cells, [1, 2], workers=1, progress=False)
    finally:
        torch.set_num_threads(threads)
    assert json.dumps(pooled) == json.dumps(serial) and len(pooled) == 2  # (NaN metrics compare as text)
