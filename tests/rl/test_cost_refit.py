"""``python -m rl.cost_refit``'s bad input (its refits on a trained student: tests/rl/test_train.py, with the
lookahead student's DAgger test, which trains one)."""

import json

import pytest

from pipeline.core.errors import ConfigError, InputMissingError
from rl.cost_refit import main, refit


def _desc(path, **fields):
    path.mkdir(parents=True, exist_ok=True)
    (path / "policy.json").write_text(json.dumps({"observation_space": {}, "net": {"head": "lookahead"}, **fields}))
    return path


def test_a_policy_that_is_not_a_dagger_student_is_one_named_error(tmp_path, capsys):
    teacher = _desc(tmp_path / "teacher", kind="teacher")
    with pytest.raises(ConfigError, match=r"teacher/policy.json: produced_by.teacher: expected a DAgger-trained "
                                          r"student, got kind 'teacher'"):
        refit(teacher, ["map"])
    assert main([str(teacher)]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    student = _desc(tmp_path / "full", kind="student", produced_by={"teacher": "../teacher", "dagger_iterations": 0})
    with pytest.raises(InputMissingError, match="no DAgger iterations"):
        refit(student, ["map"])
    with pytest.raises(ConfigError, match=r"--terms: expected a comma-separated subset of \['all', 'map', 'peds'\], "
                                          r"got 'goal'"):
        refit(student, ["map", "goal"])
    assert main([str(tmp_path / "missing")]) == 2
    assert main([str(student), "--soft-tau", "0"]) == 2
    assert not any(p.name != "policy.json" for p in tmp_path.rglob("*") if p.is_file())
