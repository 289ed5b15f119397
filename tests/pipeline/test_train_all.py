"""``icrowdnav train-all`` (pipeline.verbs.train_all): the teacher first, the other variants as independent jobs on
the local pool; every config checked before anything runs; a failed variant named with its log; a failed teacher
skips the students; the real ``train`` reached through a child process. The same on a real Ray cluster:
tests/pipeline/core/test_executor.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline import cli
from pipeline.core.errors import ConfigError
from pipeline.verbs.train_all import make_plan, run_plan, split_args

STANDIN = "tests.pipeline.standin_train"


def standin(data: Path, seconds: float = 0.2, fail: tuple[str, ...] = ()) -> None:
    """Settings of the stand-in ``train`` (tests/pipeline/standin_train.py) for runs into ``data``."""
    data.mkdir(parents=True, exist_ok=True)
    (data / "standin.json").write_text(json.dumps({"seconds": seconds, "fail": list(fail)}))


def runs(data: Path, variant: str) -> list[tuple[float, str, list[str]]]:
    """(start time, parent process title, arguments) of each run of the stand-in for ``variant``."""
    lines = (data / "checkpoints" / "policy" / variant / "runs.txt").read_text().splitlines()
    return [(float(t), parent, rest.split(" ")) for t, parent, rest in (line.split(" ", 2) for line in lines)]


def test_plan_puts_the_teacher_first_and_passes_the_rest_through(tmp_path):
    own, rest = split_args(["--variants", "[full, teacher]", "--profile", "smoke", "--jobs=2",
                            "--data-dir", str(tmp_path), "--workers", "1"])
    assert own == {"variants": "[full, teacher]", "jobs": "2"}
    assert rest == ["--profile", "smoke", "--data-dir", str(tmp_path), "--workers", "1"]
    plan = make_plan(["--variants", "[sarl_om, teacher, full]", "--profile", "smoke", "--data-dir", str(tmp_path),
                      "--workers", "1", "--executor", "local"])
    assert plan.waves == [["teacher"], ["sarl_om", "full"]] and plan.jobs == 1 and plan.executor == "local"
    assert plan.cpus_per_variant == 1 and plan.logs == tmp_path / "logs"  # default: the variants' own workers
    assert make_plan(["--variants", "vint", "--data-dir", str(tmp_path)]).waves == [["vint"]]


@pytest.mark.parametrize("argv, match", [
    (["--variants", "[full, nosuch]"], r"train-all.variants: expected distinct names from .*nosuch"),
    (["--variants", "[full, full]"], "expected distinct names"),
    (["--variants", "[]"], "expected at least one variant"),
    (["--jobs", "0"], r"train-all.jobs: expected an integer >= 1, got '0'"),
    (["--cpus_per_variant", "two"], "train-all.cpus_per_variant: expected an integer >= 1"),
    (["--executor", "dask"], "train-all.executor: expected one of"),
    (["--variant", "full"], "--variant is set per job"),
    (["--executor", "local", "--ray_address", "10.0.0.1:6379"], "train-all.ray_address"),
    (["--workers", "0"], "train.workers: expected an integer >= 1, got 0"),
    (["--jobs"], "option --jobs needs a value"),
])
def test_bad_arguments_are_one_named_error_before_anything_runs(tmp_path, capsys, argv, match):
    with pytest.raises(ConfigError, match=match):
        make_plan([*argv, "--data-dir", str(tmp_path / "data")] if argv != ["--jobs"] else argv)
    rc = cli.main(["train-all", *argv, "--data-dir", str(tmp_path / "data")] if argv != ["--jobs"]
                  else ["train-all", *argv])
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert rc == 2 and len(err) == 1
    assert not (tmp_path / "data").exists()


def test_variants_run_as_jobs_teacher_first_with_resume(tmp_path):
    data = tmp_path / "data"
    standin(data, seconds=0.5)
    plan = make_plan(["--variants", "[sarl_om, teacher, vint]", "--data-dir", str(data), "--jobs", "2",
                      "--executor", "local"])
    results = run_plan(plan, module=STANDIN)
    assert [(r["name"], r["returncode"]) for r in results] == [("teacher", 0), ("sarl_om", 0), ("vint", 0)]
    got = {v: runs(data, v) for v in ("teacher", "sarl_om", "vint")}
    assert all(len(r) == 1 for r in got.values())
    done_teacher = float((data / "checkpoints" / "policy" / "teacher" / "done").read_text())
    assert min(got["sarl_om"][0][0], got["vint"][0][0]) >= done_teacher  # the students start after the teacher
    assert abs(got["sarl_om"][0][0] - got["vint"][0][0]) < 0.45  # --jobs 2: side by side
    argv = got["vint"][0][2]
    assert argv[:3] == ["train", "--variant", "vint"] and argv[-3:] == ["--resume", "--executor", "local"]
    assert (data / "logs" / "train-vint.log").read_text().startswith("$ ")
    # --overwrite is passed as given, without --resume
    run_plan(make_plan(["--variants", "vint", "--data-dir", str(data), "--overwrite"]), module=STANDIN)
    assert "--resume" not in runs(data, "vint")[1][2] and "--overwrite" in runs(data, "vint")[1][2]


def test_a_failed_variant_is_named_and_a_failed_teacher_skips_the_students(tmp_path):
    data = tmp_path / "data"
    standin(data, fail=("sarl_om",))
    res = run_plan(make_plan(["--variants", "[sarl_om, vint]", "--data-dir", str(data)]), module=STANDIN)
    assert [(r["name"], r["returncode"]) for r in res] == [("sarl_om", 3), ("vint", 0)]  # the others go on
    standin(tmp_path / "d2", fail=("teacher",))
    res = run_plan(make_plan(["--variants", "[teacher, full]", "--data-dir", str(tmp_path / "d2")]), module=STANDIN)
    assert [(r["name"], r["returncode"]) for r in res] == [("teacher", 3), ("full", None)]
    assert not (tmp_path / "d2" / "checkpoints" / "policy" / "full").exists()


def test_the_real_train_runs_in_a_child_and_its_error_is_named(tmp_path, capsys):
    """``full`` without a teacher: the real ``train`` fails with its named error; train-all exits 2 naming the
    variant, its exit status and the log's last line."""
    data = tmp_path / "data"
    rc = cli.main(["train-all", "--variants", "[full]", "--profile", "smoke", "--data-dir", str(data)])
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert rc == 2 and len(err) == 1, err
    assert "1 of 1 variants did not finish: full (exit 2, log" in err[0] and "teacher" in err[0]
    assert "error:" in (data / "logs" / "train-full.log").read_text()
    assert not (data / "checkpoints" / "policy" / "full").exists()
