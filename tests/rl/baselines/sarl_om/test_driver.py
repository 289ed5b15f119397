"""SARL*-OM's driver: the same actions in a fresh process; a corrupt checkpoint names the file."""

import json
import subprocess
import sys
from dataclasses import replace

import pytest

from pipeline.core.errors import CorruptArtifactError
from rl.baselines import sarl_om as S
from sim.env import CrowdNavEnv
from sim.wrappers import with_privileges
from tests.rl.baselines.sarl_om.helpers import ROOT

# every test here needs the package's `trained` fixture (a training run, 20-35 s on 2 cores)
pytestmark = pytest.mark.slow


def test_driver_in_a_fresh_process_reproduces_the_actions(trained, tmp_path):
    ckpt, sim_cfg, _, _ = trained

    def drive() -> list[int]:
        env = with_privileges(CrowdNavEnv(config=replace(sim_cfg, obs_mode="privileged", action_type="discrete")),
                              "privileged")
        drv = S.Driver(ckpt)
        obs, info = env.reset(seed=123)
        drv.reset(obs, info)
        acts = []
        for _ in range(15):
            a = drv.act(obs, info)
            acts.append(a)
            obs, _, term, trunc, info = env.step(a)
            if term or trunc:
                break
        assert drv.bev_panel().shape == (32, S.Config().om_sectors)
        return acts

    mine = drive()
    code = (
        "import json, sys\n"
        "from dataclasses import replace\n"
        "from pathlib import Path\n"
        "from rl.baselines import sarl_om as S\n"
        "from sim.env import CrowdNavEnv, SimConfig\n"
        "from sim.wrappers import with_privileges\n"
        f"sim = replace(SimConfig(), scene={str(sim_cfg.scene)!r}, density=0.0, max_episode_s=5.0, "
        "obs_mode='privileged', action_type='discrete')\n"
        "env = with_privileges(CrowdNavEnv(config=sim), 'privileged')\n"
        f"drv = S.Driver(Path({str(ckpt)!r}))\n"
        "obs, info = env.reset(seed=123)\n"
        "drv.reset(obs, info)\n"
        "acts = []\n"
        f"for _ in range({len(mine)}):\n"
        "    a = drv.act(obs, info); acts.append(a); obs, _, _, _, info = env.step(a)\n"
        "print(json.dumps(acts))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout.strip().splitlines()[-1]) == mine


def test_corrupt_checkpoint_names_the_file(trained, tmp_path):
    import shutil

    ckpt = tmp_path / "sarl_om"
    shutil.copytree(trained[0], ckpt)
    (ckpt / "policy.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(CorruptArtifactError, match="policy.safetensors"):
        S.Driver(ckpt)
