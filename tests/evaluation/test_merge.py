"""Merging eval runs of one protocol (evaluation.merge): the merged report equals one over all rows, renaming, and
the runs it refuses."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from evaluation.merge import main, merge, parse_run
from pipeline.core.errors import ConfigError


def _run(root, method: str, wins: int, seeds=range(10), scene_seed: int = 120000, scenes=("office_lobby",),
         methods=None):
    """An eval run's files: ``method`` (or each of ``methods``) succeeds on the first ``wins`` seeds of each scene
    at 0.2."""
    root.mkdir(parents=True)
    rows = [{"method": m, "scene": scene, "density": 0.2, "seed": s, "outcome": "x",
             "success": int(k < wins), "collision": int(k >= wins), "timeout": 0,
             "nav_time_s": 10.0 if k < wins else float("nan"), "path_length_m": 6.0 if k < wins else float("nan"),
             "tpz_s": 1.0} for m in (methods or [method]) for scene in scenes for k, s in enumerate(seeds)]
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
        merge([(a, None, None), (_run(tmp_path / "b", "no_i2", 4, seeds=range(1, 11)), None, None)])
    with pytest.raises(ConfigError, match="not the protocol"):
        merge([(a, None, None), (_run(tmp_path / "c", "no_i2", 4, scene_seed=7), None, None)])
    with pytest.raises(ConfigError, match="'full' in office_lobby @ 0.2 is already in"):
        merge([(a, None, None), (_run(tmp_path / "d", "full", 4), None, None)])
    assert main([str(a), str(a) + ":again", "--out", str(tmp_path / "o"), "--ref", "dwa"]) == 2
    assert "--ref" in capsys.readouterr().err
    assert main([str(a), "--out", str(tmp_path / "o")]) == 2  # one run is not a merge
    assert not (tmp_path / "o").exists()
    assert parse_run("data/eval/x:full2") == (Path("data/eval/x"), "full2", None)
    assert parse_run("data/eval/x") == (Path("data/eval/x"), None, None)
    assert parse_run("data/eval/x@warehouse,blind_corner:w") == (Path("data/eval/x"), "w", ("warehouse", "blind_corner"))
    with pytest.raises(ConfigError, match="after '@'"):
        parse_run("data/eval/x@")


def test_cells_from_several_runs_make_one_table_and_a_run_gives_only_the_scenes_asked(tmp_path):
    """A six-cell table from a lobby run and a warehouse run; a third run's lobby rows are taken, its warehouse
    rows (another version of the scene) are not."""
    lobby = _run(tmp_path / "lobby", "", 8, methods=["full", "no_i2"])
    wh = _run(tmp_path / "wh", "", 6, scenes=("warehouse",), methods=["full", "no_i2"])
    light = _run(tmp_path / "light", "sarl_om", 9, scenes=("office_lobby", "warehouse"))
    (light / "scenarios").mkdir()
    (light / "scenarios" / "episodes.jsonl").write_text(json.dumps(
        {"method": "sarl_om", "scene": "blind_corner", "density": 0.0, "seed": 1, "outcome": "success", "success": 1,
         "collision": 0, "timeout": 0, "tpz_s": 0.0}) + "\n")
    rows, _ = merge([parse_run(str(lobby)), parse_run(str(light))])  # without @ every cell of the run comes along
    assert {(r["method"], r["scene"]) for r in rows} >= {("sarl_om", "warehouse")}
    out = tmp_path / "out"
    assert main([str(lobby), str(wh), f"{light}@office_lobby", "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    assert set(res) == {"office_lobby@0.2", "warehouse@0.2"}
    assert set(res["office_lobby@0.2"]) == {"full", "no_i2", "sarl_om"} and set(res["warehouse@0.2"]) == {"full", "no_i2"}
    pooled = json.loads((out / "paired.json").read_text())["pooled"]
    assert pooled["no_i2"]["n_cells"] == 2 and pooled["no_i2"]["sr"]["n"] == 20
    assert pooled["sarl_om"]["n_cells"] == 1 and pooled["sarl_om"]["sr"]["n"] == 10
    md = (out / "report.md").read_text()
    assert "10 episodes per cell and method" in md and "(office_lobby only)" in md
    assert not (out / "scenarios").exists() and "blind_corner" not in md  # light's scenario was not asked for
    again = _run(tmp_path / "again", "full", 3)  # the merged folder is a run of the protocol: it merges again
    rows, _ = merge([parse_run(f"{out}@full"), parse_run(f"{again}:full_again")])
    assert sorted({r["method"] for r in rows}) == ["full", "full_again"] and len(rows) == 30
    with pytest.raises(ConfigError, match=r"expected scenes, scenarios or methods the run holds \(blind_corner, "
                                          r"office_lobby, sarl_om, warehouse\), got \['corridor'\]"):
        merge([parse_run(str(lobby)), parse_run(f"{light}@corridor")])
    rows, _ = merge([parse_run(str(lobby)), parse_run(f"{wh}@no_i2")])  # a method named: the run's other one stays out
    assert {(r["method"], r["scene"]) for r in rows if r["scene"] == "warehouse"} == {("no_i2", "warehouse")}
    with pytest.raises(ConfigError, match="'full' in warehouse @ 0.2 is already in"):
        merge([parse_run(str(wh)), parse_run(str(lobby)), parse_run(str(wh))])
