"""Tests of pipeline.core.artifacts: atomic writes and crash-safe output directories."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.core import artifacts
from pipeline.core.artifacts import (
    OutputDir,
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
    require_input,
)
from pipeline.core.errors import InputMissingError, OutputExistsError


def names(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_atomic_writes(tmp_path: Path) -> None:
    p = atomic_write_text(tmp_path / "a" / "b.txt", "hello")
    assert p.read_text() == "hello"
    atomic_write_bytes(p, b"\x00\x01")
    assert p.read_bytes() == b"\x00\x01"
    j = atomic_write_json(tmp_path / "c.json", {"b": 1, "a": Path("x/y")})
    assert j.read_text() == '{\n  "a": "x/y",\n  "b": 1\n}\n'
    assert names(tmp_path) == ["a", "c.json"]
    assert names(tmp_path / "a") == ["b.txt"]


def test_atomic_write_failure_keeps_old_content_and_removes_temp(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    p = atomic_write_text(tmp_path / "f.txt", "old")

    def boom(src: object, dst: object) -> None:
        raise OSError("disk on fire")

    monkeypatch.setattr(artifacts.os, "replace", boom)
    with pytest.raises(OSError, match="disk on fire"):
        atomic_write_text(p, "new")
    assert p.read_text() == "old"
    assert names(tmp_path) == ["f.txt"]


def test_atomic_write_json_unserialisable_writes_nothing(tmp_path: Path) -> None:
    with pytest.raises(TypeError, match="not JSON serialisable"):
        atomic_write_json(tmp_path / "x.json", {"a": object()})
    assert names(tmp_path) == []


def test_require_input(tmp_path: Path) -> None:
    f = atomic_write_text(tmp_path / "in.txt", "x")
    assert require_input(f, "episodes") == f
    with pytest.raises(InputMissingError) as e:
        require_input(tmp_path / "nope", "rollout dataset", "run `icrowdnav rollout` first")
    assert str(e.value) == f"missing rollout dataset: {tmp_path / 'nope'}; run `icrowdnav rollout` first"


def test_new_creates_final_only_on_success(tmp_path: Path) -> None:
    final = tmp_path / "out"
    with OutputDir(final, "new") as od:
        assert od.path != final and od.path.parent == tmp_path
        (od.path / "a.txt").write_text("a")
        assert not final.exists()
    assert names(final) == ["a.txt"]
    assert names(tmp_path) == ["out"]


def test_new_on_existing_raises_and_leaves_it_untouched(tmp_path: Path) -> None:
    final = tmp_path / "out"
    final.mkdir()
    (final / "keep.txt").write_text("precious")
    with pytest.raises(OutputExistsError) as e, OutputDir(final, "new"):
        pytest.fail("body must not run")
    assert str(e.value) == (
        f"output directory {final} already exists; pass --overwrite to replace it or --resume to continue it"
    )
    assert names(final) == ["keep.txt"] and (final / "keep.txt").read_text() == "precious"
    assert names(tmp_path) == ["out"]


def test_new_on_empty_existing_dir_is_fine(tmp_path: Path) -> None:
    final = tmp_path / "out"
    final.mkdir()
    with OutputDir(final, "new") as od:
        (od.path / "a.txt").write_text("a")
    assert names(final) == ["a.txt"]


@pytest.mark.parametrize("mode", ["new", "overwrite"])
def test_exception_inside_leaves_final_untouched_and_no_staging(tmp_path: Path, mode: str) -> None:
    final = tmp_path / "out"
    if mode == "overwrite":
        final.mkdir()
        (final / "old.txt").write_text("old")
    with pytest.raises(RuntimeError, match="crash"), OutputDir(final, mode) as od:  # type: ignore[arg-type]
        (od.path / "half.txt").write_text("half")
        raise RuntimeError("crash")
    if mode == "overwrite":
        assert names(final) == ["old.txt"]
        assert names(tmp_path) == ["out"]
    else:
        assert names(tmp_path) == []


def test_overwrite_replaces(tmp_path: Path) -> None:
    final = tmp_path / "out"
    final.mkdir()
    (final / "old.txt").write_text("old")
    with OutputDir(final, "overwrite") as od:
        (od.path / "new.txt").write_text("new")
        assert (final / "old.txt").exists()  # old output stays until the new one is complete
    assert names(final) == ["new.txt"]
    assert names(tmp_path) == ["out"]  # no .old / .staging left


def test_resume_writes_in_place(tmp_path: Path) -> None:
    final = tmp_path / "out"
    with OutputDir(final, "resume") as od:
        assert od.path == final
        (od.path / "part1.txt").write_text("1")
    with pytest.raises(RuntimeError), OutputDir(final, "resume") as od:
        (od.path / "part2.txt").write_text("2")
        raise RuntimeError("interrupted")
    assert names(final) == ["part1.txt", "part2.txt"]  # resume keeps partial work


def test_resume_removes_what_a_writer_killed_mid_atomic_write_left_and_keeps_a_live_writers(tmp_path: Path) -> None:
    """A SIGKILL between an atomic write's create and rename leaves ``.<target>.<pid>.<random>.tmp``; resuming the
    directory deletes it (it is never part of the output) but not the temporary file of a writer still running."""
    final = tmp_path / "out"
    atomic_write_text(final / "rows.jsonl", "old\n")
    code = ("import sys, time; from pathlib import Path; from pipeline.core.artifacts import atomic_write_with; "
            "atomic_write_with(Path(sys.argv[1]), lambda f: (f.write(b'half'), f.flush(), print('in', flush=True), "
            "time.sleep(60)))")
    killed = subprocess.Popen([sys.executable, "-c", code, str(final / "sub" / "rows.jsonl")],
                              stdout=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[3])
    assert killed.stdout.readline() == "in\n"
    killed.kill()
    killed.wait()
    left = [p.name for p in (final / "sub").iterdir()]
    assert len(left) == 1 and left[0].startswith(f".rows.jsonl.{killed.pid}.") and left[0].endswith(".tmp")
    live = final / f".rows.jsonl.{os.getpid()}.abcdefgh.tmp"  # this process is alive: its write may still finish
    live.write_text("")
    assert artifacts.stale_atomic_temps(final) == [final / "sub" / left[0]]
    with OutputDir(final, "resume"):
        pass
    assert sorted(p.relative_to(final).as_posix() for p in final.rglob("*")) == [live.name, "rows.jsonl", "sub"]
    assert (final / "rows.jsonl").read_text() == "old\n"


def test_stale_staging_of_dead_pid_is_cleaned(tmp_path: Path) -> None:
    final = tmp_path / "out"
    stale = tmp_path / f".out.staging-{dead_pid()}"
    stale.mkdir()
    (stale / "junk").write_text("x")
    alive = tmp_path / f".out.staging-{os.getppid()}"  # a live process: left alone
    alive.mkdir()
    with OutputDir(final, "new") as od:
        (od.path / "a").write_text("a")
    assert names(tmp_path) == [alive.name, "out"]


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="zombies are read from Linux's /proc")
def test_a_killed_process_still_dying_or_unreaped_leaves_no_staging_dir(tmp_path: Path) -> None:
    """A staging dir whose process is a zombie (killed, not reaped) is stale; one left by a process that was still
    alive when the run started and died during it is removed once the run has published its output."""
    final = tmp_path / "out"
    zombie = subprocess.Popen(["true"])  # exits at once; a zombie until waited for
    while Path(f"/proc/{zombie.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
        time.sleep(0.01)
    (tmp_path / f".out.staging-{zombie.pid}").mkdir()
    dying = subprocess.Popen(["sleep", "60"])
    (tmp_path / f".out.staging-{dying.pid}").mkdir()
    try:
        with OutputDir(final, "new") as od:
            assert not (tmp_path / f".out.staging-{zombie.pid}").exists()  # cleaned on entry
            assert (tmp_path / f".out.staging-{dying.pid}").exists()  # alive: left alone
            dying.kill()
            dying.wait()
            (od.path / "a").write_text("a")
    finally:
        zombie.wait()
        dying.kill()
        dying.wait()
    assert names(tmp_path) == ["out"]


def test_interrupted_overwrite_restores_old(tmp_path: Path) -> None:
    final = tmp_path / "out"
    old = tmp_path / f".out.old-{dead_pid()}"
    old.mkdir()
    (old / "result.txt").write_text("old result")
    with pytest.raises(OutputExistsError), OutputDir(final, "new"):
        pass
    assert (final / "result.txt").read_text() == "old result"
    assert names(tmp_path) == ["out"]


def test_bad_mode() -> None:
    with pytest.raises(ValueError, match="expected one of new, overwrite, resume, got 'append'"):
        OutputDir(Path("x"), "append")  # type: ignore[arg-type]


def test_json_default_numpy(tmp_path: Path) -> None:
    np = pytest.importorskip("numpy")
    p = atomic_write_json(tmp_path / "n.json", {"a": np.float32(1.5), "b": np.arange(3)})
    assert json.loads(p.read_text()) == {"a": 1.5, "b": [0, 1, 2]}


def test_failed_publish_keeps_old_output(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    final = tmp_path / "out"
    final.mkdir()
    (final / "old.txt").write_text("old")
    real_rename = os.rename

    def flaky_rename(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
        if ".staging-" in os.fspath(src):
            raise OSError("rename failed")
        real_rename(src, dst)

    monkeypatch.setattr(artifacts.os, "rename", flaky_rename)
    with pytest.raises(OSError, match="rename failed"), OutputDir(final, "overwrite") as od:
        (od.path / "new.txt").write_text("new")
    assert names(final) == ["old.txt"]
    assert names(tmp_path) == ["out"]
