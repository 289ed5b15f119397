"""``python -m rl.figures``: the DAgger runs of several students in one figure; bad checkpoints are named errors."""

import json

import pytest

from pipeline.core.errors import CorruptArtifactError, InputMissingError
from rl.figures import DAGGER_KEYS, dagger_iterations, main, parse_ckpt


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
