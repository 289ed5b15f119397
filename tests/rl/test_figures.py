"""``python -m rl.figures``: the DAgger runs (or PPO runs) of several checkpoints in one figure; bad checkpoints are
named errors."""

import json

import pytest

from pipeline.core.errors import CorruptArtifactError, InputMissingError
from rl.figures import DAGGER_KEYS, dagger_iterations, main, parse_ckpt, ppo_log, uniform_loss


def _student(path, n_iters=3, **drop):
    path.mkdir(parents=True)
    iters = [{"iteration": k, "beta": 0.5 ** k, "frames": 1000 - 100 * k, "aggregate_frames": sum(
        1000 - 100 * j for j in range(k + 1)), "bc_loss_new_before": 4.6 - 0.3 * k, "bc_loss_new_after": 3.5 - 0.2 * k,
        "rollout_success_rate": 0.9 - 0.2 * k, "timing": {"total_s": 1.0}} for k in range(n_iters)]
    for key in drop:
        del iters[-1][key]
    (path / "metrics.json").write_text(json.dumps({"variant": "no_bev", "dagger": iters}))
    return path


def test_two_students_in_one_png_and_the_iterations_read_in_order(tmp_path, capsys):
    a, b = _student(tmp_path / "a" / "no_bev"), _student(tmp_path / "b" / "no_bev", n_iters=5)
    out = tmp_path / "fig" / "dagger.png"
    assert main([str(a), f"{b}:more_frames", "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "2 DAgger runs" in capsys.readouterr().out
    iters = dagger_iterations(b)
    assert [it["iteration"] for it in iters] == list(range(5)) and set(iters[0]) == set(DAGGER_KEYS)
    assert iters[2]["aggregate_frames"] == 1000 + 900 + 800



def test_the_uniform_loss_comes_from_the_checkpoints_action_count(tmp_path):
    """ln n of policy.json's actions: the level a cloning that learned nothing stays at (drawn on the loss panels)."""
    a = _student(tmp_path / "a" / "no_i2")
    assert uniform_loss(a) is None  # no policy.json: no line
    (a / "policy.json").write_text(json.dumps({"actions": {"type": "discrete", "n": 105}}))
    assert uniform_loss(a) == pytest.approx(4.6540, abs=1e-4)
    assert main([str(a), "--out", str(tmp_path / "f.png")]) == 0
    (a / "policy.json").write_text(json.dumps({"actions": {"type": "continuous"}}))
    assert uniform_loss(a) is None

def test_labels():
    assert parse_ckpt("/x/ckpt/policy/no_bev:big") == (parse_ckpt("/x/ckpt/policy/no_bev")[0], "big")
    assert parse_ckpt("/x/ckpt/policy/no_bev")[1] == "policy/no_bev"


def test_a_teacher_a_missing_key_and_a_missing_file_are_named(tmp_path, capsys):
    teacher = tmp_path / "teacher"
    teacher.mkdir()
    (teacher / "metrics.json").write_text(json.dumps({"variant": "teacher", "ppo_steps": 0}))
    with pytest.raises(CorruptArtifactError, match=r"teacher/metrics.json: field 'dagger': expected a non-empty list"):
        dagger_iterations(teacher)
    bad = _student(tmp_path / "bad", bc_loss_new_before=None)
    with pytest.raises(CorruptArtifactError, match=r"field 'dagger\[2\]'.*missing \['bc_loss_new_before'\]"):
        dagger_iterations(bad)
    (bad / "metrics.json").write_text("{not json")
    with pytest.raises(CorruptArtifactError, match="bad/metrics.json: expected JSON"):
        dagger_iterations(bad)
    with pytest.raises(InputMissingError, match="nowhere/metrics.json"):
        dagger_iterations(tmp_path / "nowhere")
    out = tmp_path / "never.png"
    assert main([str(teacher), "--out", str(out)]) == 2
    assert "error:" in capsys.readouterr().err and not out.exists()


def _finetuned(path, parts=((0, 4), (4, 8)), warmup=2048, run="finetune"):
    """A checkpoint whose PPO SB3 logged in ``len(parts)`` runs (a resumed one: finetune_0, _1; a teacher's: ppo_*)."""
    from torch.utils.tensorboard import SummaryWriter

    path.mkdir(parents=True)
    for k, (a, b) in enumerate(parts):
        w = SummaryWriter(str(path / "tb" / f"{run}_{k}"))
        for i in range(a, b):
            step = 512 * (i + 1)
            w.add_scalar("rollout/ep_rew_mean", 10.0 - i, step)
            w.add_scalar("train/entropy_loss", -2.5 - 0.1 * i, step)
            w.add_scalar("train/approx_kl", 0.0 if step <= warmup else 0.02, step)
        w.close()
    (path / "policy.json").write_text(json.dumps({"produced_by": {"ppo_finetune_steps": 512 * parts[-1][1],
                                                                  "ppo_critic_warmup_steps": warmup}}))
    return path


def test_ppo_runs_side_by_side_resumed_parts_in_step_order(tmp_path, capsys):
    a, b = _finetuned(tmp_path / "a" / "no_bev"), _finetuned(tmp_path / "b" / "teacher", parts=((0, 6),), warmup=0,
                                                              run="ppo")
    log, warmup = ppo_log(a)
    assert warmup == 2048 and [s for s, _ in log["rollout/ep_rew_mean"]] == [512 * (i + 1) for i in range(8)]
    assert log["train/entropy_loss"][0] == (512, pytest.approx(2.5))  # plotted as the entropy itself
    assert [s for s, _ in ppo_log(b)[0]["rollout/ep_rew_mean"]] == [512 * (i + 1) for i in range(6)]  # a teacher's
    out = tmp_path / "ppo.png"
    assert main(["--ppo", f"{a}:slow", f"{b}:fast", "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "2 PPO runs" in capsys.readouterr().out


def test_a_student_never_finetuned_is_named(tmp_path, capsys):
    plain = _student(tmp_path / "plain")
    with pytest.raises(InputMissingError, match=r"plain/tb: no PPO logs"):
        ppo_log(plain)
    out = tmp_path / "never.png"
    assert main(["--ppo", str(plain), "--out", str(out)]) == 2
    assert "no PPO logs" in capsys.readouterr().err and not out.exists()
