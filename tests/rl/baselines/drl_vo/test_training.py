"""Training DRL-VO: it learns a trivial scene (warm start + PPO) and reports its budget."""

from dataclasses import replace

import pytest
import torch

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
    assert list((trained["ckpt"] / "tb").glob("ppo_*/events.out.tfevents.*")), "PPO's curves in the checkpoint's tb/"


def test_learning_curve_points_are_saved_and_evaluated_on_the_same_seeds(trained, tmp_path):
    """``curve_steps: [128]`` saves the warm start (0) and the policy at 128 PPO steps; ``learning_curve`` runs the
    acceptance episodes on each and appends the final checkpoint's table at its budget (256)."""
    from rl.baselines import drl_vo
    from rl.baselines.common import curve_points, load_baseline
    from rl.figures import plot_learning_curve
    from rl.stage import AcceptanceConfig, learning_curve

    points = curve_points(trained["ckpt"])
    assert [(b, unit) for b, unit, _ in points] == [(0, "ppo_env_steps"), (128, "ppo_env_steps")]
    start, _ = load_baseline(points[0][2], "drl_vo", drl_vo.build_policy)
    bc, _ = load_baseline(trained["ckpt"] / "bc", "drl_vo", drl_vo.build_policy)
    _, mid = load_baseline(points[1][2], "drl_vo", drl_vo.build_policy)
    assert all(torch.equal(a, b) for a, b in zip(start.state_dict().values(), bc.state_dict().values(), strict=True))
    assert mid["produced_by"]["ppo_env_steps"] == 128 and mid["produced_by"]["expert_episodes"] == 8
    cfg = replace(trained["cfg"], acceptance=AcceptanceConfig(scenes=[trained["scene"]], densities=[0.0], episodes=2))
    final = {"table": {"empty_room@0": {"n": 2, "sr": 0.5, "collision": 0.0, "timeout": 0.5, "nav_time_s": 5.0,
                                        "tpz_s": 0.0}}}
    rows = learning_curve(cfg, points, trained["summary"]["budget"], final)
    assert [r["budget"] for r in rows] == [0, 128, 256] and {r["unit"] for r in rows} == {"ppo_env_steps"}
    assert rows[-1]["table"] is final["table"] and rows[-1]["pooled_sr"] == 0.5
    for r in rows[:2]:
        (cell,) = r["table"].values()
        assert cell["n"] == 2 and r["pooled_sr"] == cell["sr"]
    plot_learning_curve(rows, tmp_path / "curve.png", "drl_vo")
    assert (tmp_path / "curve.png").stat().st_size > 0
