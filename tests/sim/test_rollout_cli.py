"""Tests of the rollout stage through the command line (pipeline.cli.main and ``python -m pipeline``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipeline import cli
from sim.scene import load_scene
from sim.trace import OUTCOMES, EpisodeTrace

REPO = Path(__file__).resolve().parents[2]
TINY = ["--scenes", "office_lobby", "--densities", "0.05", "--episodes", "2", "--figures", "1", "--videos", "0",
        "--workers", "1"]


def run_cli(capsys, argv):
    rc = cli.main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    data = tmp_path_factory.mktemp("rollout") / "data"
    argv = ["rollout", "--data-dir", str(data), *TINY]
    rc = cli.main(argv)
    return data, argv, rc


def test_tiny_run_writes_every_output(tiny_run):
    data, _, rc = tiny_run
    assert rc == 0
    out = data / "rollouts" / "expert"
    for name in ("episodes.jsonl", "summary.json", "summary.md", "manifest.json", "config.yaml", "seeds.json"):
        assert (out / name).is_file(), name
    rows = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert len(rows) == 2
    assert [r["seed"] for r in rows] == [0, 1]
    for r in rows:
        assert r["scene"] == "office_lobby" and r["density"] == 0.05 and r["method"] == "expert"
        assert r["outcome"] in OUTCOMES and r["success"] == float(r["outcome"] == "success")
        trace = EpisodeTrace.load_npz(out / "traces" / f"office_lobby_d0.05_s{r['seed']}.npz")
        assert trace.outcome == r["outcome"] and trace.n_steps == r["steps"] and trace.seed == r["seed"]
        assert trace.scene == "office_lobby" and trace.n_peds == load_scene("office_lobby").layout().ped_count(0.05)
    pngs = sorted((out / "figures").glob("*.png"))
    assert [p.name for p in pngs] == ["office_lobby_d0.05_s0.png"]  # figures: 1 -> first episode only
    assert pngs[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and pngs[0].stat().st_size > 5000
    assert not list((out / "videos").glob("*.mp4"))
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary) == {"office_lobby_d0.05"}
    md = (out / "summary.md").read_text()
    assert "office_lobby" in md and "|" in md
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stage"] == "rollout"
    assert manifest["counts"]["episodes"] == 2
    recorded = {o["path"] for o in manifest["outputs"]}
    assert {"episodes.jsonl", "summary.json", "figures/office_lobby_d0.05_s0.png"} <= recorded
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    assert cfg["scenes"] == ["office_lobby"] and cfg["densities"] == [0.05] and cfg["episodes"] == 2
    assert json.loads((out / "seeds.json").read_text())["seeds"] == [0, 1]


def test_running_again_is_a_no_op(tiny_run, capsys):
    data, argv, _ = tiny_run
    out = data / "rollouts" / "expert"
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    rc, stdout, _ = run_cli(capsys, argv)
    assert rc == 0
    assert "up to date" in stdout
    after = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    assert after == before


def test_changed_config_refuses_to_overwrite(tiny_run, capsys):
    data, argv, _ = tiny_run
    rc, _, err = run_cli(capsys, [*argv, "--episodes", "3"])
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "--overwrite" in lines[0]


def _bad_yaml(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("name: broken\nbounds: [0, 1, 0\n")
    return str(p)


def _wrong_field(tmp_path):
    p = tmp_path / "lab.yaml"
    p.write_text("name: lab\nsplit: train\nbounds: [0, 5, 0, 5]\nobstacles:\n  - sphere: {center: [1, 1]}\n")
    return str(p)


BAD = [
    (lambda t: ["--scenes", "nowhere"], ["unknown scene 'nowhere'", "office_lobby"]),
    (lambda t: ["--densities", "-0.1"], ["densities", "-0.1"]),
    (lambda t: ["--densities", "abc"], ["densities", "abc"]),
    (lambda t: ["--sim.camera.width_px", "0"], ["camera resolution", "0x"]),
    (lambda t: ["--profile", "nope"], ["unknown profile 'nope'", "default"]),
    (lambda t: ["--scenes", _bad_yaml(t)], ["broken.yaml", "YAML"]),
    (lambda t: ["--scenes", _wrong_field(t)], ["lab.yaml", "obstacles[0]", "sphere"]),
    (lambda t: ["--scenes", str(t / "nowhere" / "missing.yaml")], ["missing.yaml", "not found"]),
    (lambda t: ["--episodes", "0"], ["episodes", "0"]),
    (lambda t: ["--workers", "0"], ["workers"]),
    (lambda t: ["--sim.obs_mode", "pixels"], ["sim.obs_mode", "pixels"]),
    (lambda t: ["--sim.colour", "red"], ["sim.colour"]),
    (lambda t: ["--no-such-key", "1"], ["no_such_key"]),
]


@pytest.mark.parametrize("make_args,words", BAD, ids=[
    "unknown-scene", "negative-density", "density-not-a-number", "bad-resolution", "unknown-profile",
    "malformed-scene-yaml", "bad-scene-field", "missing-scene-file", "zero-episodes", "zero-workers",
    "bad-obs-mode", "unknown-sim-key", "unknown-key"])
def test_bad_input_exits_2_with_one_error_line_and_writes_nothing(tmp_path, capsys, make_args, words):
    data = tmp_path / "data"
    tiny = list(TINY)
    extra = make_args(tmp_path)
    # replace a TINY option if the bad one overrides it
    for k in range(0, len(extra), 2):
        if extra[k] in tiny:
            i = tiny.index(extra[k])
            del tiny[i:i + 2]
    rc, _, err = run_cli(capsys, ["rollout", "--data-dir", str(data), *tiny, *extra])
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("error: ")
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert not data.exists()


def test_subprocess_bad_input(tmp_path):
    data = tmp_path / "data"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.run([sys.executable, "-m", "pipeline", "rollout", "--data-dir", str(data), "--scenes", "nowhere"],
                       cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: unknown scene 'nowhere'")
    assert not data.exists()


def test_rollout_help_lists_the_sim_keys(capsys):
    rc, out, _ = run_cli(capsys, ["rollout", "--help"])
    assert rc == 0
    for key in ("--scenes", "--densities", "--episodes", "--sim.camera.width_px", "--sim.density"):
        assert key in out


def test_rollout_with_density_zero(tmp_path, capsys):
    data = tmp_path / "data"
    rc, _, _ = run_cli(capsys, ["rollout", "--data-dir", str(data), "--scenes", "hallway", "--densities", "0",
                                "--episodes", "1", "--figures", "0", "--videos", "0"])
    assert rc == 0
    rows = (data / "rollouts" / "expert" / "episodes.jsonl").read_text().splitlines()
    assert json.loads(rows[0])["outcome"] == "success"
