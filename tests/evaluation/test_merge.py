"""Merging eval runs of one protocol (evaluation.merge): the merged report equals one over all rows, renaming, and
the runs it refuses."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from evaluation.merge import main, merge, parse_run
from pipeline.core.errors import ConfigError


def _run(root, method: str, wins: int, seeds=range(10), scene_seed: int = 120000):
    """An eval run's files: ``method`` succeeds on the first ``wins`` seeds of the lobby at 0.2."""
    root.mkdir(parents=True)
    rows = [{"method": method, "scene": "office_lobby", "density": 0.2, "seed": s, "outcome": "x",
             "success": int(k < wins), "collision": int(k >= wins), "timeout": 0,
             "nav_time_s": 10.0 if k < wins else float("nan"), "path_length_m": 6.0 if k < wins else float("nan"),
             "tpz_s": 1.0} for k, s in enumerate(seeds)]
    (root / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    eps = [{"seed": s, "scene_seed": scene_seed, "goal": 0, "trial": k} for k, s in enumerate(seeds)]
    (root / "seeds.json").write_text(json.dumps({"benchmark": {"episodes": eps}}))
    return root


def test_merged_runs_give_the_paired_report_of_their_methods(tmp_path):
    a, b = _run(tmp_path / "a", "full", 8), _run(tmp_path / "b", "no_i2", 4)
    again = _run(tmp_path / "c", "full", 6)  # a second training of full, renamed
    out = tmp_path / "out"
    assert main([str(a), str(b), f"{again}:full_again", "--out", str(out)]) == 0
    pr = json.loads((out / "paired.json").read_text())
    cell = pr["cells"]["office_lobby@0.2"]
    assert cell["no_i2"]["sr"]["a_only"] == 4 and cell["no_i2"]["sr"]["b_only"] == 0
    assert cell["full_again"]["sr"]["a_only"] == 2
    res = json.loads((out / "results.json").read_text())
    assert set(res["office_lobby@0.2"]) == {"full", "no_i2", "full_again"}
    md = (out / "report.md").read_text()
    assert "| iCrowdNav (full) | 10 | 80.0%" in md and "| w/o I² | 10 | 40.0%" in md and "(as `full_again`)" in md
    assert (out / "figures" / "sr_by_cell.png").stat().st_size > 0
    assert len((out / "episodes.jsonl").read_text().splitlines()) == 30


def test_a_run_on_a_subset_of_the_episodes_merges_and_pairs_on_the_common_ones(tmp_path):
    """A method capped by ``eval --method_episodes`` ran the first episodes of the same protocol."""
    a = _run(tmp_path / "a", "full", 8)
    (tmp_path / "b").mkdir()
    b = _run(tmp_path / "b" / "run", "no_i2", 2, seeds=range(4))
    (b / "seeds.json").write_text((a / "seeds.json").read_text())  # the same protocol, 4 of its 10 episodes run
    main([str(a), str(b), "--out", str(tmp_path / "out")])
    pr = json.loads((tmp_path / "out" / "paired.json").read_text())["cells"]["office_lobby@0.2"]["no_i2"]
    assert pr["n_pairs"] == 4 and pr["sr"]["a_only"] == 2
    md = (tmp_path / "out" / "report.md").read_text()
    assert "episodes per cell `full` 10, `no_i2` 4" in md and "| w/o I² | 4 | 50.0%" in md


def test_runs_of_another_protocol_or_the_same_method_are_refused(tmp_path, capsys):
    a = _run(tmp_path / "a", "full", 8)
    with pytest.raises(ConfigError, match="not the protocol"):
        merge([(a, None), (_run(tmp_path / "b", "no_i2", 4, seeds=range(1, 11)), None)])
    with pytest.raises(ConfigError, match="not the protocol"):
        merge([(a, None), (_run(tmp_path / "c", "no_i2", 4, scene_seed=7), None)])
    other_cell = _run(tmp_path / "e", "no_i2", 4)
    rows = [json.loads(line) for line in (other_cell / "episodes.jsonl").read_text().splitlines()]
    (other_cell / "episodes.jsonl").write_text("".join(json.dumps({**r, "density": 0.1}) + "\n" for r in rows))
    with pytest.raises(ConfigError, match="not the protocol"):
        merge([(a, None), (other_cell, None)])
    with pytest.raises(ConfigError, match="already in"):
        merge([(a, None), (_run(tmp_path / "d", "full", 4), None)])
    assert main([str(a), str(a) + ":again", "--out", str(tmp_path / "o"), "--ref", "dwa"]) == 2
    assert "--ref" in capsys.readouterr().err
    assert main([str(a), "--out", str(tmp_path / "o")]) == 2  # one run is not a merge
    assert not (tmp_path / "o").exists()
    assert parse_run("data/eval/x:full2") == (Path("data/eval/x"), "full2")
    assert parse_run("data/eval/x") == (Path("data/eval/x"), None)
