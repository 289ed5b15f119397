"""Tests of the icrowdnav command line (pipeline.cli), with a fake stage defined here."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml

from pipeline import cli
from pipeline.core.artifacts import pid_alive
from pipeline.core.config import PROFILES_ENV, BaseStageConfig
from pipeline.core.executor import map_jobs
from pipeline.core.stage import Stage
from tests.terminal import sigint_as_in_a_terminal

REPO = Path(__file__).resolve().parents[2]
BODY_CALLS: list[Path] = []


@dataclass
class CamConfig:
    width_px: int = field(default=64, metadata={"help": "camera image width"})


@dataclass
class FakeSimConfig:
    camera: CamConfig = field(default_factory=CamConfig)
    scenes: list[str] = field(default_factory=lambda: ["lobby"])


@dataclass
class FakeConfig(BaseStageConfig):
    episodes: int = field(default=2, metadata={"help": "number of fake episodes"})
    max_episode_s: float = field(default=30.0, metadata={"help": "episode time limit"})
    record_video: bool = field(default=False, metadata={"help": "also write a video"})
    input_path: Path | None = field(default=None, metadata={"help": "optional input"})
    sim: FakeSimConfig = field(default_factory=FakeSimConfig)


def fake_body(cfg: FakeConfig, out: Path) -> dict[str, int | float | str]:
    BODY_CALLS.append(out)
    for i in range(cfg.episodes):
        (out / f"ep{i}.json").write_text(json.dumps({"i": i, "width": cfg.sim.camera.width_px}))
    return {"episodes": cfg.episodes, "video": str(cfg.record_video).lower(), "limit_s": cfg.max_episode_s}


FAKE_STAGE = Stage(
    name="fake",
    config_cls=FakeConfig,
    help="writes fake episodes for the CLI tests",
    output_dir=lambda cfg: cfg.data_dir / "fake",
    inputs=lambda cfg: [cfg.input_path] if cfg.input_path else [],
    body=fake_body,
)


def _busy_job(job: tuple[Path, int]) -> int:
    """3 s of busy work; notes its worker's pid when it starts and when it ends."""
    out, i = job
    (out / f"start_{i}").write_text(str(os.getpid()))
    t = time.monotonic()
    while time.monotonic() - t < 3.0:
        pass
    (out / f"end_{i}").write_text(str(os.getpid()))
    return i


def busy_body(cfg: FakeConfig, out: Path) -> dict[str, int]:
    map_jobs(_busy_job, [(out, i) for i in range(12)], 2, "busy", progress=False)
    return {"jobs": 12}


# an in-place stage (like record, train, eval) whose body keeps two pool workers busy
BUSY_STAGE = Stage(name="busy", config_cls=FakeConfig, help="busy pool jobs for the signal tests",
                   output_dir=lambda cfg: cfg.data_dir / "busy", inputs=lambda cfg: [], body=busy_body,
                   resumable=True, in_place=True)


def hello(argv: list[str]) -> int:
    """Prints its arguments (a non-stage verb)."""
    print("hello", *argv)
    return 3


@pytest.fixture(autouse=True)
def setup(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    profiles = tmp_path / "profiles"
    profiles.mkdir()
    (profiles / "default.yaml").write_text("fake:\n  episodes: 3\n")
    (profiles / "smoke.yaml").write_text("common:\n  max_episode_s: 5\nfake:\n  episodes: 1\n")
    monkeypatch.setenv(PROFILES_ENV, str(profiles))
    monkeypatch.setitem(cli.VERBS, "fake", "tests.pipeline.test_cli:FAKE_STAGE")
    monkeypatch.setitem(cli.VERBS, "hello", "tests.pipeline.test_cli:hello")
    monkeypatch.setitem(cli.VERBS, "ghost", "tests.pipeline.no_such_module:STAGE")
    BODY_CALLS.clear()


def files_under(d: Path) -> list[Path]:
    return [p for p in d.rglob("*") if p.is_file()] if d.exists() else []


def test_run_and_rerun(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "data"
    argv = [
        "fake", "--data-dir", str(data), "--profile", "smoke", "--max-episode-s", "2.5",
        "--sim.camera.width_px=8", "--record-video", "--sim.scenes", "a,b", "--seed", "4",
    ]  # fmt: skip
    assert cli.main(argv) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert out == [f"fake: done -> {data / 'fake'} (episodes=1, video=true, limit_s=2.5)"]
    resolved = yaml.safe_load((data / "fake" / "config.yaml").read_text())
    assert resolved["profile"] == "smoke" and resolved["seed"] == 4
    assert resolved["sim"] == {"camera": {"width_px": 8}, "scenes": ["a", "b"]}
    manifest = json.loads((data / "fake" / "manifest.json").read_text())
    assert manifest["command"] == ["icrowdnav", *argv]

    assert cli.main(argv) == 0
    assert "up to date" in capsys.readouterr().out
    assert len(BODY_CALLS) == 1

    assert cli.main([*argv, "--episodes", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: output directory") and "--overwrite" in err[0]

    assert cli.main([*argv, "--episodes", "2", "--overwrite"]) == 0
    assert len(BODY_CALLS) == 2 and len(list((data / "fake").glob("ep*.json"))) == 2


def test_profile_default_and_bool_forms(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "data"
    assert cli.main(["fake", f"--data-dir={data}", "--record-video", "false", "--no-overwrite"]) == 0
    assert "(episodes=3, video=false, limit_s=30)" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--episodes", "abc"],
            "error: config key 'episodes' in command line: expected int, got 'abc' (str)",
        ),
        (["--sim.camera.widht-px", "3"], "error: unknown config key 'sim.camera.widht_px' in command line"),
        (["--record-video=maybe"], "error: config key 'record_video' in command line: expected bool"),
        (["--profile", "papr"], "error: unknown profile 'papr'"),
        (["--overwrite", "--resume"], "error: config keys 'overwrite' and 'resume' exclude each other"),
        (["--seed", "-1"], "error: config key 'seed': expected an int >= 0, got -1"),
        (["--input-path", "/nonexistent/x"], "error: missing input of stage 'fake': /nonexistent/x"),
        (["--config", "/nonexistent/c.yaml"], "error: missing config file: /nonexistent/c.yaml"),
        (["stray"], "error: unexpected argument 'stray'"),
        (["--episodes"], "error: option --episodes needs a value"),
    ],
)
def test_user_errors_print_one_line_and_write_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    data = tmp_path / "data"
    assert cli.main(["fake", "--data-dir", str(data), *args]) == 2
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(message)
    assert captured.out == ""
    assert files_under(data) == []
    assert BODY_CALLS == []


def test_config_file_between_profile_and_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "data"
    cfg_file = tmp_path / "mine.yaml"
    cfg_file.write_text("fake:\n  episodes: 4\n  max_episode_s: 9\n")
    assert cli.main(["fake", "--data-dir", str(data), "--config", str(cfg_file), "--episodes", "5"]) == 0
    assert "(episodes=5, video=false, limit_s=9)" in capsys.readouterr().out


def test_verb_help_lists_keys(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["fake", "--help"]) == 0
    out = capsys.readouterr().out
    assert "writes fake episodes for the CLI tests" in out
    for key in [
        "data_dir",
        "seed",
        "overwrite",
        "episodes",
        "max_episode_s",
        "sim.camera.width_px",
        "sim.scenes",
    ]:
        assert f"--{key} " in out
    assert "camera image width" in out and "list[str]" in out and "default 64" in out
    assert "default, smoke" in out  # profiles


@pytest.mark.slow
def test_top_level_help_lists_verbs(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "fake" in out and "writes fake episodes for the CLI tests" in out
    assert "Prints its arguments (a non-stage verb)." in out
    assert "ghost" in out and "unavailable" in out
    assert "rollout" in out
    assert cli.main([]) == 2
    assert "commands:" in capsys.readouterr().out


def test_the_verb_list_reads_help_lines_without_importing_the_verbs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Listing the verbs must not import their modules (each loads its stage's libraries: ~10 s for all): a verb
    module that raises when imported still lists its ``Stage(help=...)`` and its function's docstring line."""
    (tmp_path / "probe_verb_module.py").write_text(
        "from pipeline.core.stage import Stage\n"
        "raise RuntimeError('imported to list the verbs')\n"
        "STAGE = Stage(name='probe', config_cls=None, help='the probe stage help', output_dir=None, inputs=None,\n"
        "              body=None)\n"
        "def main(argv):\n"
        "    \"\"\"the probe function help\n\n    More lines.\"\"\"\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(cli.VERBS, "probe", "probe_verb_module:STAGE")
    monkeypatch.setitem(cli.VERBS, "probe-fn", "probe_verb_module:main")
    monkeypatch.setitem(cli.VERBS, "probe-missing", "probe_verb_module:NOTHING")
    listing = cli.format_verbs()
    assert "the probe stage help" in listing and "the probe function help" in listing
    assert "More lines" not in listing
    assert "probe_verb_module" not in sys.modules
    # an object the source does not name literally is imported: here that raises, so the verb shows unavailable
    line = next(row for row in listing.splitlines() if row.strip().startswith("probe-missing"))
    assert "(unavailable: imported to list the verbs)" in line
    assert "probe_verb_module" not in sys.modules  # the failed import left nothing behind


@pytest.mark.slow
def test_every_verb_lists_the_help_line_its_object_has() -> None:
    """The help line read from a verb module's source is the one its imported object carries."""
    for name, target in cli.VERBS.items():
        if name in ("fake", "hello", "ghost"):  # this file's test verbs
            continue
        obj = cli.resolve_verb(name)
        expected = obj.help if isinstance(obj, Stage) else (obj.__doc__ or "").strip().splitlines()[0]
        assert cli.static_verb_help(target) == expected, name


def test_unknown_and_unavailable_verbs(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["nope"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("error: unknown command 'nope'; available commands: ")
    assert cli.main(["ghost"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "error: command 'ghost' is not available: module tests.pipeline.no_such_module does not exist"
    ]


def test_callable_verb_gets_argv_and_returns_status(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["hello", "--x", "1"]) == 3
    assert capsys.readouterr().out == "hello --x 1\n"


def test_register_verb(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cli, "VERBS", dict(cli.VERBS))
    cli.register_verb("fake2", "tests.pipeline.test_cli:FAKE_STAGE")
    assert cli.resolve_verb("fake2") is FAKE_STAGE
    with pytest.raises(ValueError, match="module.path:OBJECT"):
        cli.register_verb("bad", "no_colon")


@pytest.mark.slow
def test_python_dash_m_pipeline() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline", "--help"], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    assert "commands:" in proc.stdout and "rollout" in proc.stdout


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the workers' pids are read from the run's files")
@pytest.mark.parametrize(("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signalled_stage_stops_its_pool_and_says_what_is_kept(tmp_path: Path, sig: signal.Signals,
                                                                  status: int) -> None:
    """SIGTERM to the run (not its process group: what ``kill PID``, a scheduler or a CI timeout sends) unwinds it
    like Ctrl-C: the pool's workers are stopped with it, no queued job is begun, and one ``error:`` line names the
    signal and where the finished work is kept (before, SIGTERM ended the run with no line)."""
    code = ("import sys\nfrom pipeline import cli\n"
            "cli.VERBS['busy'] = 'tests.pipeline.test_cli:BUSY_STAGE'\n"
            "raise SystemExit(cli.main(['busy', '--data-dir', sys.argv[1]]))")
    env = {**os.environ, PROFILES_ENV: str(tmp_path / "profiles")}
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)], cwd=REPO, env=env, text=True,
                            stderr=subprocess.PIPE, preexec_fn=sigint_as_in_a_terminal)  # Ctrl-C as in a terminal
    out = tmp_path / "busy"
    workers: set[int] = set()
    try:
        t = time.monotonic()
        while len(workers) < 2 and time.monotonic() - t < 120:
            workers = {int(x) for p in out.glob("start_*") if (x := p.read_text())} if out.is_dir() else set()
            time.sleep(0.05)
        assert len(workers) == 2, "two pool workers did not start"
        os.kill(proc.pid, sig)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == status, err
        lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
        assert lines == [f"error: busy stopped by {sig.name}: what it finished is kept in {out}; rerun with "
                         "--resume to continue"], err
        assert "Traceback" not in err
        # stop_pool joins its workers before the line is printed: none is left, none ran on
        assert not [p for p in workers if pid_alive(p)]
        assert not list(out.glob("end_*")) and len(list(out.glob("start_*"))) == 2
    finally:
        proc.kill()
        for p in workers:
            if pid_alive(p):
                os.kill(p, signal.SIGKILL)
