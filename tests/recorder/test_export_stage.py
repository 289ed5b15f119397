"""End-to-end tests of the ``export`` stage (``icrowdnav export`` = ``python -m pipeline export``).

A tiny finished recording (``icrowdnav record``) is exported once per module and shared (the lerobot import
alone costs ~15 s); the tests check that stock lerobot loads it, that the dataset doctor accepts it, its
provenance, the up-to-date no-op, the refusal after the recording changed, and bad input (exit 2, one
``error:`` line, nothing under ``datasets/``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipeline import cli
from recorder.mcap.reader import count_frames

REPO = Path(__file__).resolve().parents[2]
TINY = ["--scenes", "hallway", "--densities", "0.05", "--episodes", "2", "--sim.max-episode-s", "2.0",
        "--sim.camera.width-px", "64", "--sim.camera.height-px", "48", "--workers", "1"]
REPO_ID = "test/tiny"
MCAPS = ["hallway_d0.05_s0.mcap", "hallway_d0.05_s1.mcap"]


def run_cli(capsys, argv: list[str]) -> tuple[int, str, str]:
    rc = cli.main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def sha256(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {p.relative_to(root).as_posix(): (p.stat().st_mtime_ns, p.stat().st_size) for p in root.rglob("*")}


def record(data: Path, *extra: str, capsys=None) -> None:
    assert cli.main(["record", "--data-dir", str(data), *TINY, *extra]) == 0
    if capsys is not None:
        capsys.readouterr()  # so that the next command's output stands alone


def export_argv(data: Path, repo_id: str = REPO_ID, run_name: str = "expert") -> list[str]:
    return ["export", "--data-dir", str(data), "--run-name", run_name, "--repo-id", repo_id]


def one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("error: "), err
    return lines[0]


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    """A tiny finished recording (2 episodes) and its export to ``datasets/test/tiny``; returns DATA_DIR.
    Tests must not modify it."""
    data = tmp_path_factory.mktemp("export") / "data"
    record(data)
    assert cli.main(export_argv(data)) == 0
    return data


# ---------------------------------------------------------------------------------------------------- 6. export
def test_export_is_a_stock_lerobot_dataset_with_provenance(exported, capsys):
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    raw = exported / "raw" / "expert"
    root = exported / "datasets" / "test" / "tiny"
    assert sorted(os.listdir(exported / "datasets" / "test")) == ["tiny"]  # no staging or old directory left
    rows = [json.loads(line) for line in (raw / "episodes.jsonl").read_text().splitlines()]
    lengths = [count_frames(raw / name) for name in MCAPS]
    assert [r["frames"] for r in rows] == lengths

    ds = LeRobotDataset(REPO_ID, root=root, video_backend="pyav")
    assert ds.num_episodes == 2
    assert ds.num_frames == len(ds) == sum(lengths) - len(lengths)  # the terminal observations stay in the MCAP
    assert ds.fps == 10
    for e, first in enumerate((0, lengths[0] - 1)):  # the first frame of each episode, videos decoded with pyav
        item = ds[first]
        assert int(item["episode_index"]) == e and int(item["frame_index"]) == 0
        for cam in ("left", "right"):
            img = item[f"observation.images.{cam}"]
            assert img.shape == (3, 48, 64) and img.dtype == torch.float32
    last = ds[len(ds) - 1]
    assert int(last["episode_index"]) == 1 and int(last["frame_index"]) == lengths[1] - 2
    assert bool(last["next.done"])

    rc, stdout, _ = run_cli(capsys, ["doctor", str(root)])
    assert rc == 0, stdout
    assert "ok:" in stdout

    manifest = json.loads((root / "manifest.json").read_text())
    assert manifest["stage"] == "export"
    assert manifest["counts"]["episodes"] == 2 and manifest["counts"]["frames"] == sum(lengths) - len(lengths)
    inputs = {r["path"]: r for r in manifest["inputs"]}
    for name in MCAPS:
        rec = inputs[f"raw/expert/{name}"]
        assert rec["sha256"] == sha256(raw / name) and rec["bytes"] == (raw / name).stat().st_size
    assert set(inputs) == {f"raw/expert/{n}" for n in os.listdir(raw) if n != "manifest.json"}
    outputs = {r["path"] for r in manifest["outputs"]}
    assert {"meta/info.json", "config.yaml"} <= outputs
    cfg = yaml.safe_load((root / "config.yaml").read_text())
    assert (cfg["run_name"], cfg["repo_id"]) == ("expert", REPO_ID)


def test_stats_json_keys_are_sorted_so_its_bytes_do_not_follow_the_hash_seed(exported):
    """lerobot aggregates the feature names in a set; the export rewrites meta/stats.json sorted at every level."""
    root = exported / "datasets" / "test" / "tiny"
    text = (root / "meta" / "stats.json").read_text()
    stats = json.loads(text)

    def sorted_everywhere(d) -> bool:
        return not isinstance(d, dict) or (list(d) == sorted(d) and all(sorted_everywhere(v) for v in d.values()))

    assert len(stats) > 5 and sorted_everywhere(stats)
    assert text == json.dumps(stats, indent=4, ensure_ascii=False, sort_keys=True)


def test_second_export_is_up_to_date_and_does_no_work(exported, capsys):
    before = snapshot(exported)
    rc, stdout, _ = run_cli(capsys, export_argv(exported))
    assert rc == 0
    assert "export: up to date" in stdout
    assert snapshot(exported) == before


def test_export_after_the_recording_changed_refuses_unless_overwrite(tmp_path, capsys):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    data = tmp_path / "data"
    record(data, capsys=capsys)
    assert run_cli(capsys, export_argv(data))[0] == 0
    root = data / "datasets" / "test" / "tiny"
    old_manifest = (root / "manifest.json").read_bytes()

    record(data, "--episodes", "3", "--resume", capsys=capsys)  # one more episode; rewrites the recording's manifest
    assert json.loads((data / "raw" / "expert" / "manifest.json").read_text())["counts"]["episodes"] == 3
    before = snapshot(root)
    rc, _, err = run_cli(capsys, export_argv(data))
    assert rc == 2
    line = one_error_line(err)
    assert str(root) in line and "not up to date" in line and "inputs changed" in line
    assert "raw/expert/hallway_d0.05_s2.mcap" in line and "--overwrite" in line
    assert "--resume" not in line  # export cannot resume
    assert snapshot(root) == before and (root / "manifest.json").read_bytes() == old_manifest

    rc, stdout, _ = run_cli(capsys, [*export_argv(data), "--overwrite"])
    assert rc == 0 and "export: done" in stdout
    assert sorted(os.listdir(data / "datasets" / "test")) == ["tiny"]
    ds = LeRobotDataset(REPO_ID, root=root, video_backend="pyav")
    assert ds.num_episodes == 3
    assert ds.num_frames == sum(count_frames(p) - 1 for p in (data / "raw" / "expert").glob("*.mcap"))
    assert run_cli(capsys, ["doctor", str(root)])[0] == 0
    assert run_cli(capsys, export_argv(data))[1].startswith("export: up to date")


def test_salvaged_then_resumed_recording_exports_only_its_episodes(tmp_path, capsys):
    from recorder.drive import drive_episode
    from recorder.mcap.writer import EpisodeWriter
    from sim.env import CameraConfig, SimConfig

    data = tmp_path / "data"
    raw = data / "raw" / "expert"
    record(data, capsys=capsys)
    # the state a SIGTERM leaves: episode 0 finished, episode 1 open (closed as a valid aborted *.partial)
    (raw / MCAPS[1]).unlink()
    for name in ("manifest.json", "config.yaml"):
        (raw / name).unlink()
    rows = (raw / "episodes.jsonl").read_text().splitlines()
    (raw / "episodes.jsonl").write_text(rows[0] + "\n")
    ep = drive_episode(SimConfig(scene="hallway", density=0.05, max_episode_s=2.0,
                                 camera=CameraConfig(width_px=64, height_px=48)), 1)
    w = EpisodeWriter(raw / MCAPS[1], ep.meta, ep.occupancy).start()
    for fr, _ in zip(ep.frames, range(10), strict=False):
        w.add(fr)
    w.abort("Interrupted")
    assert (raw / (MCAPS[1] + ".partial")).is_file()

    run_cli(capsys, ["doctor", str(raw), "--recover"])  # salvage, as the doctor's message suggests
    assert (raw / "hallway_d0.05_s1.recovered.mcap").is_file()
    record(data, "--resume", capsys=capsys)
    counts = json.loads((raw / "manifest.json").read_text())["counts"]
    assert counts["episodes"] == 2

    rc, _, err = run_cli(capsys, export_argv(data))
    assert rc == 0, err
    info = json.loads((data / "datasets" / "test" / "tiny" / "meta" / "info.json").read_text())
    assert info["total_episodes"] == counts["episodes"]


# ---------------------------------------------------------------------------------------------------- 7. bad input
def test_unfinished_recording_is_refused(tmp_path, capsys, exported):
    data = tmp_path / "data"
    raw = data / "raw" / "expert"
    raw.mkdir(parents=True)
    shutil.copy(exported / "raw" / "expert" / MCAPS[0], raw / MCAPS[0])  # finished episodes, no manifest.json
    rc, _, err = run_cli(capsys, export_argv(data))
    assert rc == 2
    line = one_error_line(err)
    assert str(raw) in line and "unfinished" in line and "manifest.json" in line
    assert "icrowdnav record --resume" in line
    assert not (data / "datasets").exists()
    assert sorted(os.listdir(data)) == ["raw"] and sorted(os.listdir(raw)) == [MCAPS[0]]


def test_unfinished_recording_is_refused_by_the_command_line(tmp_path, exported):
    data = tmp_path / "data"
    raw = data / "raw" / "expert"
    raw.mkdir(parents=True)
    shutil.copy(exported / "raw" / "expert" / MCAPS[0], raw / MCAPS[0])
    (raw / (MCAPS[1] + ".partial")).write_bytes(b"\x89MCAP0\r\n")  # and an episode killed while open
    env = dict(os.environ, PYTHONPATH=str(REPO), HF_HUB_OFFLINE="1")
    p = subprocess.run([sys.executable, "-m", "pipeline", *export_argv(data)], cwd=REPO, env=env,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    line = one_error_line(p.stderr)
    assert line == (f"error: recording {raw} is unfinished (no manifest.json); finish it with "
                    "`icrowdnav record --resume` first")
    assert not (data / "datasets").exists()


BAD = [
    pytest.param(lambda d: export_argv(d, run_name="nope"), ["missing", "raw/nope"], id="missing-recording"),
    pytest.param(lambda d: export_argv(d, repo_id="no slash"), ["repo_id", "'no slash'", "owner/name"],
                 id="repo-id-without-slash"),
    pytest.param(lambda d: export_argv(d, repo_id="a/b/c"), ["repo_id", "'a/b/c'"], id="repo-id-three-parts"),
    pytest.param(lambda d: export_argv(d, repo_id="../escape"), ["repo_id", "'../escape'"],
                 id="repo-id-escaping"),
    pytest.param(lambda d: [*export_argv(d), "--profile", "nope"], ["unknown profile 'nope'"],
                 id="unknown-profile"),
    pytest.param(lambda d: [*export_argv(d), "--workers", "0"], ["workers", "expected an int >= 1", "got 0"],
                 id="zero-workers"),
    pytest.param(lambda d: [*export_argv(d), "--executor", "dask"], ["executor", "'dask'"], id="unknown-executor"),
]


@pytest.mark.parametrize("make_argv,words", BAD)
def test_bad_input_exits_2_and_creates_no_dataset(tmp_path, capsys, exported, make_argv, words):
    data = tmp_path / "data"
    shutil.copytree(exported / "raw", data / "raw")  # a finished recording to export
    before = snapshot(data)
    rc, _, err = run_cli(capsys, make_argv(data))
    assert rc == 2
    line = one_error_line(err)
    for w in words:
        assert w in line, (w, line)
    assert not (data / "datasets").exists()
    assert snapshot(data) == before
