"""Tests of recorder.doctor_mcap: a good directory passes, each kind of damage gives one line naming its file."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from recorder.doctor_mcap import check_mcap_dir, main
from recorder.drive import drive_episode
from recorder.mcap.writer import EpisodeWriter
from tests.recorder.helpers_mcap import record_episode, rewrite, tiny_config

REPO = Path(__file__).resolve().parents[2]
DT_NS = 100_000_000


@pytest.fixture(scope="module")
def good_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("good")
    record_episode(d / "ep0.mcap", 0)
    record_episode(d / "ep1.mcap", 1)
    return d


def test_good_directory_ok(good_dir: Path, capsys) -> None:
    assert check_mcap_dir(good_dir) == []
    assert main([str(good_dir)]) == 0
    assert capsys.readouterr().out.strip() == "ok: 2 episodes, 42 frames"


def test_damaged_directory_one_line_per_problem(good_dir: Path, tmp_path: Path, capsys) -> None:
    d = tmp_path / "run"
    shutil.copytree(good_dir, d)
    src = good_dir / "ep0.mcap"
    rewrite(src, d / "gap.mcap", lambda topic, t: t != 5 * DT_NS)  # a whole frame missing
    rewrite(src, d / "hole.mcap", lambda topic, t: not (topic == "/camera/left/depth" and t == 3 * DT_NS))
    rewrite(src, d / "nometa.mcap", lambda topic, t: True, metadata=False)
    data = src.read_bytes()
    (d / "trunc.mcap").write_bytes(data[: len(data) // 2])
    # an episode finished before its end (done=False at the last frame)
    ep = drive_episode(tiny_config(), 3)
    with EpisodeWriter(d / "short.mcap", ep.meta, ep.occupancy) as w:
        for fr, _ in zip(ep.frames, range(8), strict=False):
            w.add(fr)
    # an unfinished recording, and a crash between link and unlink while publishing
    shutil.copy(src, d / "open.mcap.partial")
    os.link(d / "ep1.mcap", d / "ep1.mcap.partial")
    # what a recorder killed inside an atomic rewrite of its episode list leaves (its process is gone)
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    stale = d / f".episodes.jsonl.{gone.pid}.k2j4h1x9.tmp"
    stale.write_text("")

    problems = check_mcap_dir(d)
    by_file: dict[str, list[str]] = {}
    for line in problems:
        name = Path(line.split(": ", 1)[0]).name
        by_file.setdefault(name, []).append(line)
    assert set(by_file) == {"gap.mcap", "hole.mcap", "nometa.mcap", "trunc.mcap", "short.mcap", "open.mcap.partial",
                            "ep1.mcap.partial", stale.name}
    assert by_file[stale.name] == [f"{stale}: leftover temporary file of an interrupted write; delete it"]
    assert len(by_file["ep1.mcap.partial"]) == 1 and "second name of the finished ep1.mcap" in by_file["ep1.mcap.partial"][0]
    assert any("off the dt=100 ms grid" in x for x in by_file["gap.mcap"])
    assert any("steps" in x for x in by_file["gap.mcap"])
    assert by_file["hole.mcap"] == [f"{d / 'hole.mcap'}: 1 of 21 frames miss topics (first at t=0.300 s: "
                                    "/camera/left/depth)"]
    assert any("'episode' metadata record missing" in x for x in by_file["nometa.mcap"])
    assert len(by_file["trunc.mcap"]) == 1 and "truncated" in by_file["trunc.mcap"][0]
    assert by_file["short.mcap"] == [f"{d / 'short.mcap'}: episode does not end with done=True (last frame 7, "
                                     "t=0.700 s)"]
    assert len(by_file["open.mcap.partial"]) == 1 and "--recover" in by_file["open.mcap.partial"][0]

    assert main([str(d)]) == 1
    out = capsys.readouterr().out.strip().splitlines()
    assert out == problems

    # --recover salvages the partial; it is then reported as already recovered
    assert main([str(d), "--recover"]) == 1
    out = capsys.readouterr().out
    assert "open.mcap.partial: recovered 21 complete frames into open.recovered.mcap" in out
    assert "already recovered into open.recovered.mcap" in out
    assert not any(line.startswith(str(d / "open.recovered.mcap")) for line in check_mcap_dir(d))


def test_cli_bad_input(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "recorder.doctor_mcap", str(tmp_path / "absent")], cwd=REPO,
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip() == f"error: missing MCAP directory: {tmp_path / 'absent'}"
    assert r.stdout == ""
