"""Tests of pipeline.core.manifest and pipeline.core.stage (provenance, idempotent stage runs)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml

import pipeline
import pipeline.core.stage as stage_mod
from pipeline.core.config import BaseStageConfig, apply_dict, config_hash, from_dict
from pipeline.core.errors import ConfigError, CorruptArtifactError, InputMissingError, OutputExistsError
from pipeline.core.manifest import (
    MANIFEST_NAME,
    FileRecord,
    Manifest,
    collect_versions,
    git_info,
    hash_file,
    hash_tree,
)
from pipeline.core.stage import Stage, mode_of, run_stage, run_stage_ex

# ------------------------------------------------------------------ manifest


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def test_hash_file_and_tree(tmp_path: Path) -> None:
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "z.bin").write_bytes(b"zz")
    (tmp_path / "a.txt").write_bytes(b"a")
    (tmp_path / "manifest.json").write_text("{}")
    (tmp_path / "b" / "manifest.json").write_text("{}")  # only the top-level one is excluded
    assert hash_file(tmp_path / "a.txt") == sha(b"a")
    assert hash_tree(tmp_path) == [
        FileRecord("a.txt", sha(b"a"), 1),
        FileRecord("b/manifest.json", sha(b"{}"), 2),
        FileRecord("b/z.bin", sha(b"zz"), 2),
    ]
    assert [r.path for r in hash_tree(tmp_path, exclude=set())][1] == "b/manifest.json"
    assert len(hash_tree(tmp_path, exclude=set())) == 4
    with pytest.raises(InputMissingError):
        hash_tree(tmp_path / "nope")


def make_manifest() -> Manifest:
    return Manifest(
        stage="toy",
        params={"episodes": 2, "sim": {"dt_s": 0.1}},
        config_hash="ab" * 32,
        seed=7,
        inputs=[FileRecord("in/x.bin", "cd" * 32, 10)],
        outputs=[FileRecord("a.txt", "ef" * 32, 3)],
        counts={"episodes": 2, "success_rate": 0.5, "note": "ok"},
        created_utc="2025-01-01T00:00:00Z",
        git_commit="unknown",
        git_dirty=False,
        versions={"python": "3.11.7"},
        duration_s=1.25,
        command=["icrowdnav", "toy"],
    )


def test_manifest_round_trip(tmp_path: Path) -> None:
    m = make_manifest()
    path = m.write(tmp_path / "manifest.json")
    assert Manifest.read(path) == m
    text = path.read_text()
    assert text.startswith('{\n  "code_hash"')  # indent 2, sorted keys
    assert json.loads(text)["inputs"] == [{"bytes": 10, "path": "in/x.bin", "sha256": "cd" * 32}]


def test_manifest_read_missing(tmp_path: Path) -> None:
    with pytest.raises(InputMissingError, match=r"missing manifest: .*manifest\.json"):
        Manifest.read(tmp_path / "manifest.json")


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        ('{"stage": ', r"invalid JSON at line 1"),
        ("[1, 2]", r"expected a JSON object, got list"),
        ('{"stage": "x"}', r"missing field\(s\) params, config_hash"),
        (None, r"field 'seed' must be an int or null, got 'seven'"),
        ("bad-outputs", r"outputs\[0\] must be"),
    ],
)
def test_corrupt_manifest_names_file_and_problem(tmp_path: Path, content: str | None, problem: str) -> None:
    path = tmp_path / "manifest.json"
    data = make_manifest().to_dict()
    if content is None:
        data["seed"] = "seven"
        content = json.dumps(data)
    elif content == "bad-outputs":
        data["outputs"] = [{"path": "a"}]
        content = json.dumps(data)
    path.write_text(content)
    with pytest.raises(CorruptArtifactError) as e:
        Manifest.read(path)
    assert str(e.value).startswith(f"corrupt manifest {path}: ")
    assert re.search(problem, str(e.value))


def test_collect_versions() -> None:
    v = collect_versions()
    assert re.fullmatch(r"3\.\d+\.\d+.*", v["python"])
    assert "platform" in v
    assert v["numpy"]  # installed in the venv
    assert all(isinstance(x, str) for x in v.values())


def test_git_info(tmp_path: Path) -> None:
    assert git_info(tmp_path) == ("unknown", False)
    commit, dirty = git_info(Path(pipeline.__file__))
    assert commit == "unknown" or re.fullmatch(r"[0-9a-f]{40}", commit)
    assert isinstance(dirty, bool)


# ------------------------------------------------------------------ run_stage

CALLS: list[Path] = []


@dataclass
class ToyStageConfig(BaseStageConfig):
    episodes: int = field(default=2, metadata={"help": "episodes to write"})
    input_path: Path | None = field(default=None, metadata={"help": "optional input file or directory"})
    fail: bool = False


def toy_body(cfg: ToyStageConfig, out: Path) -> dict[str, int | float | str]:
    CALLS.append(out)
    if cfg.fail:
        (out / "half.txt").write_text("half")
        raise RuntimeError("body crashed")
    (out / "episodes").mkdir(exist_ok=True)
    for i in range(cfg.episodes):
        (out / "episodes" / f"ep{i:03d}.txt").write_text(f"episode {i} seed {cfg.seed}")
    (out / "summary.txt").write_text(f"{cfg.episodes}")
    return {"episodes": cfg.episodes, "mean_len_s": 1.5}


TOY = Stage(
    name="toy",
    config_cls=ToyStageConfig,
    help="writes toy episodes",
    output_dir=lambda cfg: cfg.data_dir / "toy",
    inputs=lambda cfg: [cfg.input_path] if cfg.input_path is not None else [],
    body=toy_body,
)
TOY_RESUMABLE = dataclasses.replace(TOY, resumable=True)


@pytest.fixture
def cfg(tmp_path: Path) -> ToyStageConfig:
    CALLS.clear()
    return from_dict(ToyStageConfig, {"data_dir": str(tmp_path / "data")}, "test")


def test_run_stage_writes_outputs_config_and_manifest(cfg: ToyStageConfig) -> None:
    m = run_stage(TOY, cfg, command=["icrowdnav", "toy"])
    out = cfg.data_dir / "toy"
    assert sorted(p.name for p in out.iterdir()) == [
        "config.yaml",
        "episodes",
        "manifest.json",
        "summary.txt",
    ]
    assert Manifest.read(out / "manifest.json") == m
    assert m.stage == "toy" and m.seed == 0 and m.command == ["icrowdnav", "toy"]
    assert m.config_hash == config_hash(cfg)
    assert m.counts == {"episodes": 2, "mean_len_s": 1.5}
    assert [r.path for r in m.outputs] == [
        "config.yaml",
        "episodes/ep000.txt",
        "episodes/ep001.txt",
        "summary.txt",
    ]
    assert m.params["episodes"] == 2
    assert yaml.safe_load((out / "config.yaml").read_text())["episodes"] == 2
    assert sorted(p.name for p in cfg.data_dir.iterdir()) == ["toy"]  # no staging dir left


def test_manifest_records_the_code_at_the_start_of_a_run(cfg: ToyStageConfig, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run during which a commit lands (hours of training) records the commit and code hash it started with."""
    import pipeline.core.stage as stage_mod

    state = {"commit": "a" * 40, "code": "start"}
    monkeypatch.setattr(stage_mod, "git_info", lambda root: (state["commit"], False))
    monkeypatch.setattr(stage_mod, "code_hash", lambda root, packages: state["code"])

    def body(c: ToyStageConfig, out: Path) -> dict[str, int]:
        state.update(commit="b" * 40, code="later")  # what a commit during the run would change
        return toy_body(c, out)

    m = run_stage(dataclasses.replace(TOY, body=body), cfg)
    assert m.git_commit == "a" * 40 and m.code_hash == "start"


def test_run_stage_twice_is_a_noop(cfg: ToyStageConfig, caplog: pytest.LogCaptureFixture) -> None:
    first = run_stage(TOY, cfg)
    caplog.set_level(logging.INFO, logger="icrowdnav")
    second, ran = run_stage_ex(TOY, cfg)
    assert len(CALLS) == 1 and not ran
    assert second == first
    assert f"toy: up to date ({cfg.data_dir / 'toy'})" in caplog.messages


def test_changed_config_raises_then_overwrite_reruns(cfg: ToyStageConfig) -> None:
    run_stage(TOY, cfg)
    changed = apply_dict(cfg, {"episodes": 3}, "test")
    with pytest.raises(OutputExistsError, match=r"already exists and is not up to date \(the config changed"):
        run_stage(TOY, changed)
    assert len(CALLS) == 1
    m = run_stage(TOY, apply_dict(changed, {"overwrite": True}, "test"))
    assert len(CALLS) == 2 and m.counts["episodes"] == 3
    assert len(list((cfg.data_dir / "toy" / "episodes").iterdir())) == 3
    run_stage(TOY, changed)  # the overwritten output is up to date for the new config
    assert len(CALLS) == 2


def test_deleted_output_is_not_up_to_date(cfg: ToyStageConfig) -> None:
    run_stage(TOY, cfg)
    (cfg.data_dir / "toy" / "summary.txt").unlink()
    with pytest.raises(OutputExistsError, match="output file summary.txt is missing"):
        run_stage(TOY, cfg)


def test_output_without_manifest_is_not_overwritten(cfg: ToyStageConfig) -> None:
    out = cfg.data_dir / "toy"
    out.mkdir(parents=True)
    (out / "foreign.txt").write_text("not ours")
    with pytest.raises(OutputExistsError, match="has no manifest.json"):
        run_stage(TOY, cfg)
    assert [p.name for p in out.iterdir()] == ["foreign.txt"]
    assert CALLS == []


def test_missing_input(cfg: ToyStageConfig) -> None:
    missing = cfg.data_dir / "rollouts" / "none"
    with pytest.raises(InputMissingError, match=re.escape(f"missing input of stage 'toy': {missing}")):
        run_stage(TOY, apply_dict(cfg, {"input_path": str(missing)}, "test"))
    assert CALLS == [] and not cfg.data_dir.exists()


def test_inputs_are_hashed_and_changes_detected(cfg: ToyStageConfig) -> None:
    src = cfg.data_dir / "rollouts"
    (src / "eps").mkdir(parents=True)
    (src / "eps" / "0.bin").write_bytes(b"0")
    (src / "meta.json").write_text("{}")
    (src / "manifest.json").write_text("{}")  # an upstream manifest is not an input
    with_input = apply_dict(cfg, {"input_path": str(src)}, "test")
    m = run_stage(TOY, with_input)
    assert m.inputs == [
        FileRecord("rollouts/eps/0.bin", sha(b"0"), 1),
        FileRecord("rollouts/meta.json", sha(b"{}"), 2),
    ]
    run_stage(TOY, with_input)
    assert len(CALLS) == 1
    (src / "eps" / "0.bin").write_bytes(b"1")
    with pytest.raises(OutputExistsError, match=r"its inputs changed \(rollouts/eps/0.bin\)"):
        run_stage(TOY, with_input)


def test_body_exception_leaves_nothing(cfg: ToyStageConfig) -> None:
    with pytest.raises(RuntimeError, match="body crashed"):
        run_stage(TOY, apply_dict(cfg, {"fail": True}, "test"))
    assert not cfg.data_dir.exists()  # not even the folders the failed run would have published into


def test_resume(cfg: ToyStageConfig) -> None:
    resume = apply_dict(cfg, {"resume": True}, "test")
    run_stage(TOY_RESUMABLE, resume)
    assert CALLS == [cfg.data_dir / "toy"]  # resumable stages write in place
    (cfg.data_dir / "toy" / MANIFEST_NAME).unlink()  # as a kill before the end leaves it
    run_stage(TOY_RESUMABLE, resume)
    assert len(CALLS) == 2  # an unfinished output: the body continues it (it skips finished work itself)
    run_stage(TOY_RESUMABLE, apply_dict(resume, {"episodes": 3}, "test"))
    assert len(CALLS) == 3  # a stale one too


def test_resume_leaves_a_finished_output_byte_for_byte(cfg: ToyStageConfig) -> None:
    """`make all ARGS=--resume` after a kill: the stages that had finished are not rewritten, since a rewritten
    config.yaml (now saying `resume: true`) is an input of the next stage and would make it rebuild."""
    run_stage(TOY_RESUMABLE, cfg)
    out = cfg.data_dir / "toy"
    after = dataclasses.replace(TOY, name="toy_after", output_dir=lambda c: c.data_dir / "toy_after")
    after_cfg = apply_dict(cfg, {"input_path": str(out)}, "test")
    run_stage(after, after_cfg)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    _, ran = run_stage_ex(TOY_RESUMABLE, apply_dict(cfg, {"resume": True}, "test"))
    assert not ran and len(CALLS) == 2
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    _, ran = run_stage_ex(after, apply_dict(after_cfg, {"resume": True}, "test"))
    assert not ran and len(CALLS) == 2  # the next stage is still up to date


def test_resume_of_an_atomic_stage_keeps_an_up_to_date_output_and_rebuilds_a_stale_one(cfg) -> None:
    """A stage that is not resumable publishes atomically: --resume (as `make record ARGS=--resume` passes it to
    export) builds a missing output, skips an up-to-date one and rebuilds a stale one (the old kept until done)."""
    resume = apply_dict(cfg, {"resume": True}, "test")
    _, ran = run_stage_ex(TOY, resume)
    assert ran and (cfg.data_dir / "toy" / MANIFEST_NAME).is_file()
    _, ran = run_stage_ex(TOY, resume)
    assert not ran
    with pytest.raises(OutputExistsError):  # without --resume a stale output is still refused
        run_stage(TOY, apply_dict(cfg, {"episodes": 3}, "test"))
    manifest, ran = run_stage_ex(TOY, apply_dict(resume, {"episodes": 3}, "test"))
    assert ran and manifest.params["episodes"] == 3
    assert sorted(p.name for p in cfg.data_dir.iterdir()) == ["toy"]  # no staging or old dir left


def test_mode_of() -> None:
    base = BaseStageConfig()
    assert mode_of(base) == "new"
    assert mode_of(dataclasses.replace(base, overwrite=True)) == "overwrite"
    assert mode_of(dataclasses.replace(base, resume=True)) == "resume"
    with pytest.raises(ConfigError, match="exclude each other"):
        mode_of(dataclasses.replace(base, resume=True, overwrite=True))


TOY_IN_PLACE = dataclasses.replace(TOY, resumable=True, in_place=True, scaffold=("seeds.json",))


def _in_place_body(work: bool):
    def body(cfg: ToyStageConfig, out: Path) -> dict:
        (out / "seeds.json").write_text("[1, 2]")
        (out / "episodes").mkdir()
        (out / "episodes" / "empty.txt").write_text("")
        if work:
            (out / "episodes" / "ep000.txt").write_text("finished episode")
        raise RuntimeError("body crashed")
    return body


def test_failed_in_place_run_without_work_leaves_nothing(cfg: ToyStageConfig) -> None:
    with pytest.raises(RuntimeError, match="body crashed"):
        run_stage(dataclasses.replace(TOY_IN_PLACE, body=_in_place_body(work=False)), cfg)
    assert not (cfg.data_dir / "toy").exists()


def test_failed_in_place_run_with_work_keeps_it_and_the_next_run_says_resume(cfg: ToyStageConfig) -> None:
    with pytest.raises(RuntimeError, match="body crashed"):
        run_stage(dataclasses.replace(TOY_IN_PLACE, body=_in_place_body(work=True)), cfg)
    assert (cfg.data_dir / "toy" / "episodes" / "ep000.txt").is_file()
    with pytest.raises(OutputExistsError, match="--resume to continue it"):
        run_stage(TOY_IN_PLACE, cfg)
    run_stage(TOY_IN_PLACE, apply_dict(cfg, {"resume": True}, "test"))
    assert (cfg.data_dir / "toy" / MANIFEST_NAME).is_file()


def test_failed_resume_of_an_existing_dir_never_removes_it(cfg: ToyStageConfig) -> None:
    out = cfg.data_dir / "toy"
    out.mkdir(parents=True)
    with pytest.raises(RuntimeError, match="body crashed"):
        run_stage(dataclasses.replace(TOY_IN_PLACE, body=_in_place_body(work=False)),
                  apply_dict(cfg, {"resume": True}, "test"))
    assert out.is_dir()


def test_resume_into_an_unwritable_output_is_a_named_error(cfg: ToyStageConfig, monkeypatch) -> None:
    import os

    out = cfg.data_dir / "toy"
    out.mkdir(parents=True)
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == out else real(p, mode))
    with pytest.raises(ConfigError, match=rf"directory not writable: {re.escape(str(out))}"):
        run_stage(TOY_IN_PLACE, apply_dict(cfg, {"resume": True}, "test"))
    assert CALLS == []


# ------------------------------------------------------------------ verify_output / release_output


def _finished_output(root: Path, files: dict[str, bytes]) -> Path:
    """A stage-like output directory: files, config.yaml and a manifest.json listing them (as run_stage writes)."""
    for rel, data in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    (root / "config.yaml").write_text("seed: 0\n")
    dataclasses.replace(make_manifest(), outputs=hash_tree(root)).write(root / MANIFEST_NAME)
    return root


def test_verify_output_accepts_an_intact_listed_file_and_hashes_it_once(tmp_path: Path, monkeypatch) -> None:
    from pipeline.core import manifest as mod

    out = _finished_output(tmp_path / "ckpt", {"w.bin": b"weights" * 100, "sub/x.bin": b"x"})
    calls = []
    monkeypatch.setattr(mod, "hash_file", lambda p: calls.append(p) or hash_file(p))
    assert mod.owning_manifest(out / "sub" / "x.bin") == out / MANIFEST_NAME
    rec = mod.verify_output(out / "w.bin")
    assert rec == FileRecord("w.bin", sha(b"weights" * 100), 700)
    assert mod.verify_output(out / "sub" / "x.bin").path == "sub/x.bin"
    assert mod.verify_output(out / "w.bin") == rec and len(calls) == 2  # the intact file is not hashed again


def test_verify_output_names_a_damaged_file_expected_and_found(tmp_path: Path) -> None:
    from pipeline.core.manifest import verify_output

    out = _finished_output(tmp_path / "ckpt", {"w.bin": b"\x01" * 64, "v.bin": b"\x02" * 64})
    good, damaged = sha(b"\x01" * 64), b"\x01" * 32 + b"\xff" * 32
    (out / "w.bin").write_bytes(damaged)  # same size, other bytes
    with pytest.raises(CorruptArtifactError) as e:
        verify_output(out / "w.bin")
    msg = str(e.value)
    assert str(out / "w.bin") in msg and "\n" not in msg
    assert f"expected sha256 {good[:16]}" in msg and f"found {sha(damaged)[:16]}" in msg
    assert str(out / MANIFEST_NAME) in msg
    (out / "v.bin").write_bytes(b"\x02" * 10)  # truncated
    with pytest.raises(CorruptArtifactError, match=r"v\.bin: expected 64 bytes .* found 10 bytes"):
        verify_output(out / "v.bin")
    with pytest.raises(InputMissingError, match="nope.bin"):
        verify_output(out / "nope.bin")


def test_verify_output_skips_files_no_manifest_lists(tmp_path: Path) -> None:
    from pipeline.core.manifest import owning_manifest, verify_output

    out = _finished_output(tmp_path / "ckpt", {"w.bin": b"w"})
    (out / "later.bin").write_bytes(b"written after the manifest")  # e.g. resume state of a later run
    assert verify_output(out / "later.bin") is None
    loose = tmp_path / "loose" / "w.bin"  # no manifest at all (a staging dir, user-given weights)
    loose.parent.mkdir()
    loose.write_bytes(b"w")
    assert verify_output(loose) is None
    (tmp_path / "loose" / MANIFEST_NAME).write_text('{"name": "some web app"}')  # not a stage's: no config.yaml
    assert owning_manifest(loose) is None and verify_output(loose) is None


def test_release_output_drops_the_manifest_that_lists_a_rewritten_file(tmp_path: Path) -> None:
    from pipeline.core.manifest import release_output, verify_output

    out = _finished_output(tmp_path / "ckpt", {"w.bin": b"old"})
    assert release_output(out / "new.bin") is None and (out / MANIFEST_NAME).is_file()  # not listed: kept
    assert release_output(out / "w.bin") == out / MANIFEST_NAME
    assert not (out / MANIFEST_NAME).exists()
    (out / "w.bin").write_bytes(b"new bytes of a resumed run")
    assert verify_output(out / "w.bin") is None  # unfinished until the stage writes a new manifest


def test_a_resumed_output_counts_every_invocation_in_its_wall(cfg: ToyStageConfig, monkeypatch) -> None:
    """An output continued in place sums its invocations' walls: a finished one's from its manifest, a killed one's
    until its last write (its ledger beside the output survives the kill); a fresh run counts itself only."""
    clock = {"t": 1000.0}
    monkeypatch.setattr(stage_mod.time, "monotonic", lambda: clock["t"])
    resume = apply_dict(cfg, {"resume": True}, "test")
    out, ledger = cfg.data_dir / "toy", cfg.data_dir / ".toy.invocation.json"

    def body_taking(seconds: float):
        def body(c, o):
            clock["t"] += seconds
            return toy_body(c, o)
        return body

    m = run_stage(dataclasses.replace(TOY_IN_PLACE, body=body_taking(60.0)), resume)
    assert (m.duration_s, m.wall_total_s, m.invocations) == (60.0, 60.0, 1) and not ledger.exists()
    m = run_stage(dataclasses.replace(TOY_IN_PLACE, body=body_taking(3.0)), resume)  # finished: left as it is
    assert (m.duration_s, m.wall_total_s, m.invocations) == (60.0, 60.0, 1)
    resume = apply_dict(resume, {"episodes": 3}, "test")  # one more episode: the finished output is continued
    m = run_stage(dataclasses.replace(TOY_IN_PLACE, body=body_taking(3.0)), resume)
    assert (m.duration_s, m.wall_total_s, m.invocations) == (3.0, 63.0, 2)
    assert Manifest.read(out / MANIFEST_NAME).wall_total_s == 63.0

    # a killed invocation: its ledger stays; it last wrote 40 s after its start
    stage_mod._begin_invocation(out)
    start = json.loads(ledger.read_text())["start_unix"]
    os.utime(out / "summary.txt", (start + 40.0, start + 40.0))
    (out / MANIFEST_NAME).unlink()  # the killed run had not finished
    m = run_stage(dataclasses.replace(TOY_IN_PLACE, body=body_taking(5.0)), resume)
    assert (m.duration_s, m.invocations) == (5.0, 4) and m.wall_total_s == pytest.approx(63.0 + 40.0 + 5.0, abs=0.01)
    assert not ledger.exists()

    m = run_stage(dataclasses.replace(TOY_IN_PLACE, body=body_taking(7.0)), apply_dict(cfg, {"overwrite": True}, "t"))
    assert (m.wall_total_s, m.invocations) == (7.0, 1)  # a fresh output starts its count again


def test_a_manifest_of_older_code_reads_as_one_invocation(tmp_path: Path) -> None:
    data = make_manifest().to_dict()
    del data["wall_total_s"], data["invocations"]
    m = Manifest.from_dict(data, tmp_path / MANIFEST_NAME)
    assert (m.wall_total_s, m.invocations) == (m.duration_s, 1)
    with pytest.raises(CorruptArtifactError, match="'invocations' must be an int"):
        Manifest.from_dict({**make_manifest().to_dict(), "invocations": "2"}, tmp_path / MANIFEST_NAME)
