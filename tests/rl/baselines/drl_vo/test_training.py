"""Training DRL-VO: it learns a trivial scene (warm start + PPO) and reports its budget."""

import pytest

from tests.rl.baselines.drl_vo.helpers import success_rate

# every test here needs the package's `trained` fixture (a training run, 20-35 s on 2 cores)
pytestmark = pytest.mark.slow


def test_learns_a_trivial_scene(trained):
    """Measured: 0.1-0.2 before (straight ahead at half speed), 1.0 after."""
    before = success_rate(trained["untrained"], trained["scene"])
    after = success_rate(trained["ckpt"], trained["scene"])
    assert after >= before + 0.4 and after >= 0.7, (before, after)
    budget = trained["summary"]["budget"]
    assert budget["expert_episodes"] == 8 and budget["ppo_env_steps"] >= 256 and budget["expert_frames"] > 0
    phases = {p for p, _, _ in trained["log"].rows}
    assert "drl_vo_bc" in phases and "drl_vo_ppo" in phases
    assert (trained["ckpt"] / "ppo" / "last.zip").is_file()
